"""The model-adequacy verdict (calibration/evaluate.py `summarize`) from per-pose residuals."""

import math

from calibration.evaluate import ADEQUATE_RATIO, summarize


def _pose(n: int, rms: float, expected: float, rms_screen: float, expected_screen: float):
    return {"n_points": n, "rms_px": rms, "expected_rms_px": expected,
            "rms_screen_px": rms_screen, "expected_rms_screen_px": expected_screen}


def test_a_misfit_hidden_by_one_pose_with_a_huge_jacobian_is_inadequate() -> None:
    """One pose near a fold of a distortion that does not fit expects 4.37 px per point
    (its screen->camera Jacobian is huge): pooled in camera px, that swamps every other
    point and the ratio says 'adequate'; in the screen plane each point weighs by its
    decoded sigma and the 2.6x misfit shows (numbers of opencv-rational on a 150-degree
    fisheye, benchmarks/inadequate_fit.py)."""
    clean = _pose(40000, 0.06, 0.05, 0.13, 0.05)
    fold = _pose(3000, 0.9, 4.37, 0.13, 0.05)
    st = summarize([clean, fold])
    assert st["noise_floor_ratio"] < ADEQUATE_RATIO  # the camera-px verdict alone: fooled
    assert math.isclose(st["noise_floor_ratio_screen"], 2.6, rel_tol=1e-9)
    assert not st["model_adequate"]


def test_adequate_when_both_ratios_are_at_the_noise_floor() -> None:
    st = summarize([_pose(5000, 0.052, 0.05, 0.049, 0.05), _pose(4000, 0.3, 0.31, 0.05, 0.05)])
    assert st["noise_floor_ratio"] < 1.1 and st["noise_floor_ratio_screen"] < 1.1
    assert st["model_adequate"]


def test_camera_ratio_still_decides_without_screen_residuals() -> None:
    """Rows without screen-plane numbers (NaN): the camera-px ratio alone decides."""
    nan = float("nan")
    assert summarize([_pose(100, 0.05, 0.05, nan, nan)])["model_adequate"]
    assert not summarize([_pose(100, 0.5, 0.05, nan, nan)])["model_adequate"]
