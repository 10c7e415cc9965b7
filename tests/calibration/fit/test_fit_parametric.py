"""OpenCV-family calibration through `dispatch.calibrate` against hw_mocks ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.fit.dispatch import calibrate
from calibration.fit.ransac import DegenerateError
from calibration.report import write_residual_report
from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import PinholeCamera, mild_pinhole, wide_fisheye
from hw_mocks.poses import look_at_pose, random_poses
from hw_mocks.synthetic import synthetic_maps

SCREEN = ScreenGeometry(1920, 1080, (0.2745, 0.2745))
SIGMA = 0.05  # decoded sigma, screen px


def _maps(cam, n: int, seed: int, outliers: float = 0.02):
    """n posed synthetic maps of a camera with a few gross decoding outliers."""
    rng = np.random.default_rng(seed)
    poses = random_poses(cam, SCREEN, n, rng)
    return [synthetic_maps(cam, p, SCREEN, sigma_px=SIGMA, rng=rng, outlier_fraction=outliers)[0]
            for p in poses], poses


@pytest.fixture(scope="module")
def pinhole_fit():
    cam = mild_pinhole()
    maps, poses = _maps(cam, 8, 11)
    return cam, maps, poses, calibrate(maps, SCREEN, "opencv5", heldout=[7])


@pytest.fixture(scope="module")
def fisheye_data():
    cam = wide_fisheye(fov_deg=150)
    maps, _ = _maps(cam, 7, 12)
    return cam, maps


def test_opencv5_recovers_mild_pinhole(pinhole_fit) -> None:
    cam, _, poses, res = pinhole_fit
    fx, fy, cx, cy = res.model.get_params()[:4]
    truth = np.array([cam.fx, cam.fy, cam.cx, cam.cy])
    np.testing.assert_allclose([fx, fy, cx, cy], truth, rtol=1e-3)
    # Errors agree with the predicted standard deviations (within 5 sigma).
    std = res.stats["param_std"]
    for name, est, true in zip(("fx", "fy", "cx", "cy"), (fx, fy, cx, cy), truth, strict=True):
        assert std[name] > 0
        assert abs(est - true) < 5 * std[name] + 1e-9, (name, est, true, std[name])
    np.testing.assert_allclose(res.model.dist, cam.dist, atol=5e-3)
    # RMS at the decoding noise level (expected camera-px RMS from the screen sigmas).
    assert 0.8 < res.stats["noise_floor_ratio"] < 1.2 and res.stats["model_adequate"]
    assert 0.8 < res.stats["rms_screen_px"] / (SIGMA * np.sqrt(2)) < 1.2
    assert len(res.stats["per_pose"]) == 7 and res.stats["training_poses"] == list(range(7))
    for est, true in zip(res.poses, poses[:7], strict=True):
        assert np.linalg.norm(est.translation - true.translation) < 0.5
    held = res.stats["heldout"]
    assert held["per_pose"][0]["pose"] == 7 and 0.8 < held["noise_floor_ratio"] < 1.3


def test_residual_map_and_report(pinhole_fit, tmp_path) -> None:
    _, _, _, res = pinhole_fit
    field = residual_map(res, 0)
    assert field.shape == (480, 640, 2) and np.isfinite(field).any()
    out = tmp_path / "res.png"
    write_residual_report(res, out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_fisheye_model_reaches_noise_floor(fisheye_data) -> None:
    cam, maps = fisheye_data
    res = calibrate(maps, SCREEN, "fisheye")
    k = res.model.get_params()
    np.testing.assert_allclose(k[:4], [cam.f, cam.f, cam.cx, cam.cy], rtol=1e-3)
    assert res.stats["model_adequate"] and res.stats["noise_floor_ratio"] < 1.2


def test_opencv5_fails_on_fisheye_with_radial_pattern(fisheye_data, tmp_path) -> None:
    _, maps = fisheye_data
    res = calibrate(maps, SCREEN, "opencv5")
    assert not res.stats["model_adequate"] and res.stats["noise_floor_ratio"] > 5
    # Systematic and radial: residuals point along the radius (noise would give ~0.5).
    pix = np.concatenate(list(res.residual_pixels.values()))
    r = np.concatenate(list(res.residuals.values()))
    k = res.model.get_params()
    e = pix - k[2:4]
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    ok = np.all(np.isfinite(r), axis=1)
    radial = np.sum(np.sum(r[ok] * e[ok], axis=1) ** 2) / np.sum(r[ok] ** 2)
    assert radial > 0.8
    write_residual_report(res, tmp_path / "bad.png")
    assert (tmp_path / "bad.png").stat().st_size > 10_000


def test_bad_inputs(pinhole_fit) -> None:
    _, maps, _, _ = pinhole_fit
    with pytest.raises(ValueError, match="training poses"):
        calibrate(maps[:3], SCREEN, "opencv5", heldout=[0])
    with pytest.raises(ValueError, match="heldout"):
        calibrate(maps, SCREEN, "opencv5", heldout=[9])
    with pytest.raises(ValueError, match="unknown key"):
        calibrate(maps[:3], SCREEN, "opencv5", options={"bogus": 1})
    with pytest.raises(ValueError, match="model"):
        calibrate(maps, SCREEN, "nonesuch")
    small, _ = _maps(mild_pinhole(320, 240), 1, 3)
    with pytest.raises(ValueError, match="image sizes differ"):
        calibrate([*maps[:3], small[0]], SCREEN, "opencv5")
    empty = synthetic_maps(mild_pinhole(), random_poses(mild_pinhole(), SCREEN, 1,
                                                        np.random.default_rng(0))[0],
                           SCREEN, rng=np.random.default_rng(0), valid_fraction=1e-4)[0]
    with pytest.raises(ValueError, match="valid pixels"):
        calibrate([*maps[:3], empty], SCREEN, "opencv5")


def test_degenerate_views_rejected() -> None:
    # Fronto-parallel views only: focal length and distance cannot be separated.
    rng = np.random.default_rng(0)
    cam = PinholeCamera(640, 480, fx=520.0, fy=520.0, cx=331.0, cy=233.5)
    views = ((400, 0), (450, 10), (500, -10))
    maps = [synthetic_maps(cam, look_at_pose(SCREEN, distance_mm=d, roll_deg=r), SCREEN,
                           sigma_px=SIGMA, rng=rng)[0] for d, r in views]
    with pytest.raises(DegenerateError, match="too similar"):
        calibrate(maps, SCREEN, "opencv5", options={"max_points_per_pose": 300})


def test_cancel_and_progress(pinhole_fit) -> None:
    from calibration.shared.progress import Cancelled

    _, maps, _, _ = pinhole_fit
    with pytest.raises(Cancelled, match="cancelled"):
        calibrate(maps[:3], SCREEN, "opencv5", cancelled=lambda: True)
    seen: list[tuple[int, int, str]] = []
    calibrate(maps[:3], SCREEN, "opencv5", options={"max_points_per_pose": 300},
              progress=lambda i, n, msg: seen.append((i, n, msg)))
    assert seen and all(0 <= i <= n for i, n, _ in seen) and "evaluating" in seen[-1][2]


def residual_map(result, pose: int) -> np.ndarray:
    """(H, W, 2) camera-px residual field of one pose, NaN where no point was evaluated."""
    w, h = result.model.image_size
    out = np.full((h, w, 2), np.nan)
    px = np.rint(result.residual_pixels[pose]).astype(np.int64)
    ok = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    out[px[ok, 1], px[ok, 0]] = result.residuals[pose][ok]
    return out
