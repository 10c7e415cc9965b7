"""Closed-form estimators vs hw_mocks truth: DLT, homography, Zhang, PnP, VP, rotation."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from calibration.fit.classic.dlt import decompose_projection, dlt_projection, ransac_dlt
from calibration.fit.classic.homography import fit_homography
from calibration.fit.classic.pnp import estimate_pose
from calibration.fit.classic.rectangle import rectangle_intrinsics, vanishing_points
from calibration.fit.classic.rotation import interview_homographies, rotation_intrinsics
from calibration.fit.classic.zhang import pose_from_homography, zhang_intrinsics
from calibration.fit.correspondences import point_set, subsample
from calibration.fit.ransac import DegenerateError
from calibration.models.parametric import OpenCV5Model
from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import PinholeCamera, mild_pinhole
from hw_mocks.poses import random_poses, rotation_only_poses
from hw_mocks.synthetic import synthetic_maps

SCREEN = ScreenGeometry(1920, 1080, (0.2745, 0.2745))


def _angle_deg(r1: np.ndarray, r2: np.ndarray) -> float:
    """Angle of the relative rotation between two rotation matrices."""
    return float(np.degrees(np.arccos(np.clip((np.trace(r1.T @ r2) - 1) / 2, -1, 1))))


def _ideal() -> PinholeCamera:
    """A distortion-free pinhole (square pixels, offset principal point)."""
    return PinholeCamera(640, 480, fx=520.0, fy=520.0, cx=331.0, cy=233.5)


def cam_size(cam: PinholeCamera) -> tuple[int, int]:
    """(width, height) of a truth camera."""
    return (cam.width, cam.height)


def _homographies(cam, poses, rng, sigma=0.05) -> list[np.ndarray]:
    """Least-squares screen(mm) -> pixel homographies of each pose's decoded maps."""
    out = []
    for pose in poses:
        maps, _ = synthetic_maps(cam, pose, SCREEN, sigma_px=sigma, rng=rng)
        pts = subsample(point_set(maps, SCREEN), 3000)
        out.append(fit_homography(pts.screen_mm[:, :2], pts.pixels))
    return out


def test_homography_exact_and_degenerate() -> None:
    rng = np.random.default_rng(1)
    h = np.array([[1.2, 0.1, 30], [-0.05, 0.9, 12], [1e-4, 2e-4, 1.0]])
    src = rng.uniform(0, 500, (40, 2))
    q = src @ h[:, :2].T + h[:, 2]
    np.testing.assert_allclose(fit_homography(src, q[:, :2] / q[:, 2:]), h, atol=1e-9)
    line = np.column_stack([np.arange(10.0), 2 * np.arange(10.0)])
    with pytest.raises(DegenerateError, match="degenerate"):
        fit_homography(line, line)
    with pytest.raises(DegenerateError, match=">= 4"):
        fit_homography(src[:3], src[:3])


def test_zhang_recovers_k_and_poses() -> None:
    rng = np.random.default_rng(2)
    cam = _ideal()
    poses = random_poses(cam, SCREEN, 5, rng)
    hs = _homographies(cam, poses, rng, sigma=1e-9)
    k = zhang_intrinsics(hs)
    np.testing.assert_allclose(k, cam.camera_matrix, rtol=1e-6, atol=1e-4)
    r, t = pose_from_homography(k, hs[0])
    assert _angle_deg(r, poses[0].rotation) < 1e-4
    np.testing.assert_allclose(t, poses[0].translation, rtol=1e-6)
    with pytest.raises(DegenerateError, match=">= 3 views"):
        zhang_intrinsics(hs[:2])


def test_dlt_ransac_pose_with_outliers() -> None:
    rng = np.random.default_rng(3)
    cam = _ideal()
    rot = random_poses(cam, SCREEN, 1, rng)[0]
    world = np.column_stack([rng.uniform(-200, 200, (400, 2)), rng.uniform(-100, 100, 400)])
    cam_pts = world @ rot.rotation.T + rot.translation + np.array([0, 0, 400.0])
    t_true = rot.translation + np.array([0, 0, 400.0])
    pix = cam.project(cam_pts) + 0.05 * rng.standard_normal((400, 2))
    ok = np.all(np.isfinite(pix), axis=1)
    world, pix = world[ok], pix[ok]
    out = rng.random(len(pix)) < 0.2
    pix[out] = rng.uniform(0, 640, (int(out.sum()), 2))
    p, inl = ransac_dlt(world, pix, 1.0, rng)
    assert np.mean(inl[~out]) > 0.95 and np.mean(inl[out]) < 0.05
    k, r, t = decompose_projection(p)
    assert _angle_deg(r, rot.rotation) < 0.1
    np.testing.assert_allclose(k, cam.camera_matrix, rtol=0.01, atol=2.0)
    np.testing.assert_allclose(t, t_true, rtol=0.01)
    with pytest.raises(DegenerateError, match="coplanar"):
        dlt_projection(np.column_stack([world[:, :2], np.zeros(len(world))]), pix)


def test_pnp_ransac_pose_with_20_percent_outliers() -> None:
    rng = np.random.default_rng(4)
    cam = mild_pinhole()
    model = OpenCV5Model((cam.width, cam.height), cam.camera_matrix, np.asarray(cam.dist))
    for pose in random_poses(cam, SCREEN, 3, rng):
        maps, _ = synthetic_maps(cam, pose, SCREEN, sigma_px=0.05, rng=rng,
                                 outlier_fraction=0.2)
        pts = subsample(point_set(maps, SCREEN, reject_outliers=False), 2000)
        r, t, inl = estimate_pose(model, pts, rng)
        assert _angle_deg(r, pose.rotation) < 0.1
        assert np.linalg.norm(t - pose.translation) < 1e-3 * np.linalg.norm(pose.translation)
        assert 0.7 < inl.mean() < 0.85  # the 20 % injected outliers are rejected


def test_local_outlier_filter_finds_injected_outliers() -> None:
    rng = np.random.default_rng(5)
    cam = mild_pinhole()
    pose = random_poses(cam, SCREEN, 1, rng)[0]
    maps, truth = synthetic_maps(cam, pose, SCREEN, sigma_px=0.05, rng=rng, outlier_fraction=0.2)
    kept = point_set(maps, SCREEN)
    u, v = kept.pixels[:, 0].astype(int), kept.pixels[:, 1].astype(int)
    assert truth["outliers"][v, u].mean() < 0.005
    assert len(kept) > 0.7 * maps.valid_count()


def test_sorting_network_sorts_every_binary_input() -> None:
    """0-1 principle: a comparator network that sorts all 2^9 binary inputs sorts any."""
    from calibration.fit.correspondences import _sort9

    bits = ((np.arange(512)[:, None] >> np.arange(9)) & 1).T.astype(np.float64)
    planes = bits.copy()
    _sort9(planes, np.empty(512))
    np.testing.assert_array_equal(planes, np.sort(bits, axis=0))


@pytest.mark.parametrize("rows", [1, 3, 16, 40])
def test_local_outliers_match_nanmedian_of_each_neighbourhood(rows, monkeypatch) -> None:
    """Median and median absolute deviation over each pixel's finite 3x3 neighbours, as
    np.nanmedian gives them, whatever the block height (image and block edges, NaN holes)."""
    import calibration.fit.correspondences as corr

    monkeypatch.setattr(corr, "_BLOCK_ROWS", rows)
    rng = np.random.default_rng(8)
    v, u = np.mgrid[0:37, 0:29]
    values = 0.7 * u + 0.2 * v + rng.normal(0, 0.02, u.shape)
    values[rng.random(u.shape) < 0.25] = np.nan
    bad = rng.random(u.shape) < 0.06
    values[bad] += rng.choice([-1, 1], bad.sum()) * rng.uniform(0.1, 5, bad.sum())
    values[0, :3] = values[:2, -1] = np.nan  # a pixel whose neighbours are nearly all missing
    sigma = rng.uniform(0.005, 0.03, u.shape)
    stack = np.stack([np.pad(values, 1, constant_values=np.nan)[dv:dv + 37, du:du + 29]
                      for dv in range(3) for du in range(3)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (all-NaN neighbourhoods)
        med = np.nanmedian(stack, axis=0)
        spread = np.nanmedian(np.abs(stack - med), axis=0)
    with np.errstate(invalid="ignore"):
        expected = np.abs(values - med) > corr._OUTLIER_SIGMAS * sigma + 2.0 * spread
    found = corr.local_outliers(values, sigma)
    np.testing.assert_array_equal(found, expected)
    assert 20 <= found.sum() <= bad.sum()  # (some injected ones fall in NaN holes)


def test_vanishing_point_intrinsics_six_views() -> None:
    rng = np.random.default_rng(6)
    cam = _ideal()
    hs = _homographies(cam, random_poses(cam, SCREEN, 6, rng), rng)
    for square in (True, False):
        k = rectangle_intrinsics([vanishing_points(h) for h in hs], cam_size(cam),
                                 square_pixels=square).k
        assert abs(k[0, 0] / cam.fx - 1) < 0.02 and abs(k[1, 1] / cam.fy - 1) < 0.02
        assert abs(k[0, 2] - cam.cx) < 0.02 * cam.fx and abs(k[1, 2] - cam.cy) < 0.02 * cam.fx
    with pytest.raises(DegenerateError, match=">= 4 views"):
        rectangle_intrinsics([vanishing_points(h) for h in hs[:3]], cam_size(cam))


def test_rotation_only_self_calibration() -> None:
    rng = np.random.default_rng(7)
    cam = PinholeCamera(640, 480, fx=520.0, fy=523.0, cx=331.0, cy=233.5)
    poses = rotation_only_poses(cam, SCREEN, 5, rng, max_rotation_deg=20.0)
    hs = _homographies(cam, poses, rng)
    k = rotation_intrinsics(interview_homographies(hs))
    np.testing.assert_allclose(np.diag(k)[:2], [cam.fx, cam.fy], rtol=0.01)
    assert abs(k[0, 2] - cam.cx) < 0.01 * cam.fx and abs(k[1, 2] - cam.cy) < 0.01 * cam.fx
    with pytest.raises(DegenerateError, match=">= 2"):
        rotation_intrinsics(interview_homographies(hs[:2]))
