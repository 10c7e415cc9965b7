"""Vanishing-point intrinsics from image lines vs hw_mocks truth: rectangle VPs, white flats,
general-motion selfcal."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.fit.classic.lines import fit_line, grid_vanishing_points, intersect
from calibration.fit.classic.quad import find_quads
from calibration.fit.classic.rectangle import rectangle_intrinsics
from calibration.fit.classic.rotation import NotPositiveDefiniteError, k_from_kkt
from calibration.fit.classic.selfcal import selfcal_intrinsics
from calibration.fit.ransac import DegenerateError
from hw_mocks.cameras import PinholeCamera
from hw_mocks.rectangles import (
    board_pixels,
    general_motion_views,
    screen_corners_px,
    two_board_scene,
    white_flat_image,
    whole_screen_poses,
)
from hw_mocks.rig import DEFAULT_SCREEN

SIZE = (640, 480)


def _cam(fy: float = 530.0) -> PinholeCamera:
    return PinholeCamera(*SIZE, fx=520.0, fy=fy, cx=331.0, cy=233.5)


def _rel_err(k: np.ndarray, cam: PinholeCamera) -> float:
    """Largest error of fx, fy (relative) and cx, cy (relative to fx)."""
    return max(abs(k[0, 0] / cam.fx - 1), abs(k[1, 1] / cam.fy - 1),
               abs(k[0, 2] - cam.cx) / cam.fx, abs(k[1, 2] - cam.cy) / cam.fx)


def test_line_fit_and_intersection_covariance() -> None:
    rng = np.random.default_rng(0)
    t = np.linspace(-50, 50, 40)
    sig = 0.2
    hits = []
    for _ in range(300):
        a = fit_line(np.c_[t, 0.5 * t + 10] + sig * rng.standard_normal((40, 2)), sigma_px=sig)
        b = fit_line(np.c_[t, -t + 100] + sig * rng.standard_normal((40, 2)), sigma_px=sig)
        hits.append((intersect(a, b).pixel(), intersect(a, b)))
    pix = np.array([h[0] for h in hits])
    np.testing.assert_allclose(pix.mean(axis=0), [60, 40], atol=0.05)
    # the propagated covariance predicts the scatter (within sampling error)
    pt = hits[0][1]
    jac = np.array([[1 / pt.p[2], 0, -pt.p[0] / pt.p[2] ** 2],
                    [0, 1 / pt.p[2], -pt.p[1] / pt.p[2] ** 2]])
    pred = np.sqrt(np.diag(jac @ pt.cov @ jac.T))
    assert np.all(np.abs(pix.std(axis=0) / pred - 1) < 0.2)


def test_rectangle_both_forms_exact_without_noise() -> None:
    rng = np.random.default_rng(1)
    cam = _cam(fy=530.0)
    boards = two_board_scene()
    views = general_motion_views(cam, boards, 6, rng)
    pairs = [grid_vanishing_points(p[0]) for p in board_pixels(cam, boards, views)]
    k = rectangle_intrinsics(pairs, SIZE).k
    assert _rel_err(k, cam) < 1e-7  # fx != fy recovered (paper's equation 4)
    sq = rectangle_intrinsics(pairs, SIZE, square_pixels=True)
    assert sq.k[0, 0] == sq.k[1, 1] and sq.stats["angle_residual_deg_rms"] > 0.1
    square_cam = _cam(fy=520.0)
    pairs = [grid_vanishing_points(p[0]) for p in board_pixels(square_cam, boards, views)]
    assert _rel_err(rectangle_intrinsics(pairs, SIZE, square_pixels=True).k, square_cam) < 1e-7
    with pytest.raises(DegenerateError, match=">= 4 views"):
        rectangle_intrinsics(pairs[:3], SIZE)


def test_quick_intrinsics_from_four_white_flats() -> None:
    rng = np.random.default_rng(2)
    cam = _cam(fy=520.0)
    poses = whole_screen_poses(cam, DEFAULT_SCREEN, 4, rng)
    pairs = []
    for pose in poses:
        quad = find_quads(white_flat_image(cam, pose, DEFAULT_SCREEN, rng))[0]
        truth = screen_corners_px(cam, pose, DEFAULT_SCREEN)
        assert np.max(np.linalg.norm(quad.corners - truth, axis=1)) < 0.3
        pairs.append(quad.vanishing_points())
    est = rectangle_intrinsics(pairs, SIZE, square_pixels=True)
    assert _rel_err(est.k, cam) < 0.02
    # the Monte Carlo std is honest: the error is within 4 sigma
    assert abs(est.k[0, 0] - cam.fx) < 4 * est.std["fx"] + 0.5


def test_white_flat_with_screen_cut_by_the_border_is_refused() -> None:
    rng = np.random.default_rng(3)
    cam = _cam()
    pose = whole_screen_poses(cam, DEFAULT_SCREEN, 1, rng)[0]
    img = white_flat_image(cam, pose, DEFAULT_SCREEN, rng)
    with pytest.raises(DegenerateError, match="touches the image border"):
        find_quads(img[:, : int(screen_corners_px(cam, pose, DEFAULT_SCREEN)[:, 0].mean())])


def _tracks(cam: PinholeCamera, n: int, sigma: float, rng: np.random.Generator) -> list:
    boards = two_board_scene()
    views = general_motion_views(cam, boards, n, rng)
    px = board_pixels(cam, boards, views, sigma_px=sigma, rng=rng)
    s = sigma if sigma > 0 else None
    return [[vp for grid in img for vp in grid_vanishing_points(grid, sigma_px=s)] for img in px]


def test_selfcal_general_motion_exact_and_at_0p1_px() -> None:
    rng = np.random.default_rng(4)
    cam = _cam(fy=530.0)
    exact = selfcal_intrinsics(_tracks(cam, 3, 0.0, rng), SIZE)
    assert _rel_err(exact.k, cam) < 1e-7 and abs(exact.k[0, 1]) < 1e-6
    for n in (4, 6):
        est = selfcal_intrinsics(_tracks(cam, n, 0.1, rng), SIZE, mc_samples=50)
        assert _rel_err(est.k, cam) < 0.01, (n, est.k)
        assert est.stats["refined"] and 0.3 < est.stats["chi2_per_dof"] < 3


def test_selfcal_errors_are_specific() -> None:
    rng = np.random.default_rng(5)
    with pytest.raises(NotPositiveDefiniteError, match="not positive definite"):
        k_from_kkt(np.diag([1.0, -1.0, 1.0]))
    tracks = _tracks(_cam(), 3, 0.0, rng)
    with pytest.raises(DegenerateError, match=">= 3 images"):
        selfcal_intrinsics(tracks[:2], SIZE)
    with pytest.raises(DegenerateError, match=">= 4 directions"):
        selfcal_intrinsics([t[:3] for t in tracks], SIZE)
    # one board only: 2 directions repeated -> three coplanar directions
    with pytest.raises(DegenerateError, match="coplanar"):
        selfcal_intrinsics([t[:2] + t[:2] for t in tracks], SIZE)
