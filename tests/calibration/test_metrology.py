"""Weighted all-pixel parametric fits and the fitted screen model, against hw_mocks truth."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from calibration.compare import ray_angle_difference
from calibration.fit.classic.parametric import fit_parametric
from calibration.fit.correspondences import point_set
from calibration.metrology.directions import directions
from calibration.metrology.lm import _Problem
from calibration.metrology.refine import fit_parametric_dense
from calibration.metrology.screen import ScreenModel
from calibration.models.parametric import FisheyeModel, OpenCV5Model, OpenCVRationalModel
from calibration.shared.plan import ScreenGeometry
from hw_mocks import cameras, poses, synthetic
from hw_mocks.panel import PanelShape

SCREEN = ScreenGeometry(1920, 1080, (0.2745, 0.2745))
REAL = PanelShape(bow_x_mm=0.5, bow_y_mm=0.3, glass_mm=1.5)
K = np.array([[500.0, 0, 320], [0, 502, 240], [0, 0, 1]])
MODELS = {
    "opencv5": lambda: OpenCV5Model((640, 480), K, [-0.11, 0.045, 4e-4, -3e-4, -0.008]),
    "rational": lambda: OpenCVRationalModel(
        (640, 480), K, [0.3, -0.05, 1e-3, -5e-4, 0.01, 0.35, -0.04, 0.02, 1e-3, -1e-3, 2e-3, 0]),
    "fisheye": lambda: FisheyeModel((640, 480), np.array([[200.0, 0, 320], [0, 201, 240],
                                                         [0, 0, 1]]), [0.012, -0.004, 8e-4, -1e-4]),
}


@pytest.mark.parametrize("name", sorted(MODELS))
def test_direction_jacobians_match_finite_differences(name: str) -> None:
    """Analytic d(direction)/d(intrinsics) agrees with central differences."""
    model = MODELS[name]()
    rng = np.random.default_rng(0)
    pix = rng.uniform(0, 1, (40, 2)) * [640, 480]
    _, jac, _ = directions(model, pix)
    p0 = model.get_params()
    for i in range(p0.size):
        h = 1e-6 * max(abs(p0[i]), 1e-2)
        model.set_params(p0 + h * np.eye(p0.size)[i])
        plus = directions(model, pix, jacobian=False)[0]
        model.set_params(p0 - h * np.eye(p0.size)[i])
        minus = directions(model, pix, jacobian=False)[0]
        model.set_params(p0)
        fd = (plus - minus) / (2 * h)
        assert np.abs(fd - jac[:, :, i]).max() <= 1e-6 * (np.abs(fd).max() + 1e-9)


def test_directions_of_a_pixel_that_does_not_undistort_are_nan_without_warnings() -> None:
    """A pixel whose undistortion does not converge (far outside a strongly distorting
    model's image) gets a NaN direction and Jacobian, silently; the others are as when
    decoded alone (the complex-step Jacobians skip it, NaN complex division warns)."""
    import warnings

    from calibration.metrology.directions import _distort_jac_xy

    model = MODELS["rational"]()
    pix = np.array([[100.0, 80.0], [320.0, 240.0], [600.0, 400.0]])
    alone = directions(model, pix)
    jac_alone = _distort_jac_xy(model, np.array([0.1, -0.2]), np.array([0.05, 0.3]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any RuntimeWarning fails the test
        dirs, jac, _ = directions(model, np.vstack([pix[:1], [[-4e4, 5e4]], pix[1:]]))
        jac_nan = _distort_jac_xy(model, np.array([0.1, np.nan, -0.2]),
                                  np.array([0.05, 0.0, 0.3]))
    assert np.isnan(dirs[1, :2]).all() and np.isnan(jac[1, :2]).all()  # (z: 1, its rows 0)
    np.testing.assert_array_equal(dirs[[0, 2, 3]], alone[0])
    np.testing.assert_array_equal(jac[[0, 2, 3]], alone[1])
    assert np.isnan(jac_nan[1]).all()
    np.testing.assert_array_equal(jac_nan[[0, 2]], jac_alone)


def test_screen_trace_matches_hw_mocks_and_its_jacobians() -> None:
    """The fit's panel model hits where hw_mocks' exact tracer does; Jacobians by FD."""
    sm = ScreenModel(SCREEN, "fit", 1.52, np.array([0.5, 0.3, 0.2, 1.5]))
    rng = np.random.default_rng(2)
    o = np.column_stack([rng.uniform(0, 500, 30), rng.uniform(0, 300, 30),
                         rng.uniform(-600, -100, 30)])
    q = rng.uniform(-0.7, 0.7, (30, 2))
    pts, jac = sm.trace(o, q)
    x, y, ok = PanelShape(0.5, 0.3, 0.2, 1.5).trace(SCREEN, o, np.column_stack([q, np.ones(30)]))
    assert ok.all()
    np.testing.assert_allclose(pts, np.column_stack([x, y]), atol=1e-9)
    for i in range(4):
        e = 1e-6 * np.eye(4)[i]
        plus = ScreenModel(SCREEN, "fit", 1.52, sm.params + e).trace(o, q, False)[0]
        minus = ScreenModel(SCREEN, "fit", 1.52, sm.params - e).trace(o, q, False)[0]
        np.testing.assert_allclose((plus - minus) / 2e-6, jac["s"][:, :, i], atol=1e-6)
    for i in range(2):
        e = np.zeros(2)
        e[i] = 1e-7
        fd = (sm.trace(o, q + e, False)[0] - sm.trace(o, q - e, False)[0]) / 2e-7
        np.testing.assert_allclose(fd, jac["q"][:, :, i], rtol=1e-6, atol=1e-5)


def _scene(cam, seed: int, panel: PanelShape | None):
    """Point sets of 6 random poses and the pixels on which to compare rays."""
    rng = np.random.default_rng(seed)
    ps = poses.random_poses(cam, SCREEN, 6, rng)
    maps = [synthetic.synthetic_maps(cam, p, SCREEN, rng=rng, sigma_px=0.05, panel=panel,
                                     )[0] for p in ps]
    seen = np.logical_or.reduce([m.mask for m in maps])
    v, u = np.nonzero(seen[::3, ::3])
    return [point_set(m, SCREEN) for m in maps], np.stack([u * 3, v * 3], 1).astype(float)


def _ray_rms(cam, model, pix: np.ndarray) -> float:
    """RMS ray angle to the truth after the best rotation."""
    return float(ray_angle_difference(model.unproject, lambda p: cam.rays(p[:, 0], p[:, 1]),
                                      (cam.width, cam.height), pixels=pix)["rms_rad"])


@pytest.mark.parametrize("family", ["opencv5", "fisheye"])
def test_all_pixel_fit_is_honest_and_beats_sampled_opencv(family: str) -> None:
    """Every pixel, weighted: intrinsics within 4 sigma of truth, chi2 ~ 1, smaller sigma."""
    cam = cameras.mild_pinhole(160, 120) if family == "opencv5" else cameras.wide_fisheye(160, 120)
    pts, _ = _scene(cam, 4, None)
    pts[0].screen_px[::500] += 3.0  # decoding errors the 3x3 outlier filter let through
    _, _, _, sampled, _ = fit_parametric_dense(pts, (160, 120), family, SCREEN,
                                       {"points": "sampled", "max_points_per_pose": 300})
    model, _, used, stats, dense = fit_parametric_dense(pts, (160, 120), family, SCREEN)
    assert dense is not None and stats["dense"]["dropped_outliers"] > 0
    assert 0.9 < stats["reduced_chi2"] < 1.1
    truth = ([cam.fx, cam.fy, cam.cx, cam.cy] if family == "opencv5"
             else [cam.f, cam.f, cam.cx, cam.cy])
    std = np.array(list(stats["param_std"].values())[:4])
    assert np.all(np.abs(model.get_params()[:4] - truth) < 4 * std)
    # 60x the points: the intrinsics' sigma shrinks several-fold (and the truth stays inside).
    assert np.all(std < 0.4 * np.array(list(sampled["param_std"].values())[:4]))
    assert stats["screen"] == {"mode": "flat", "glass_index": 1.52}
    assert sum(len(p) for p in used) == stats["dense"]["points"]


def test_screen_fit_recovers_bow_and_glass() -> None:
    """Bowed panel behind glass: "fit" finds it within 3 sigma and the camera as if ideal."""
    cam = cameras.mild_pinhole(200, 150)
    ideal_pts, pix = _scene(cam, 11, None)
    real_pts, _ = _scene(cam, 11, REAL)
    ideal = _ray_rms(cam, fit_parametric_dense(ideal_pts, (200, 150), "opencv5", SCREEN)[0], pix)
    flat = _ray_rms(cam, fit_parametric_dense(real_pts, (200, 150), "opencv5", SCREEN)[0], pix)
    model, _, used, stats, _ = fit_parametric_dense(real_pts, (200, 150), "opencv5", SCREEN,
                                                    {"screen": "fit"})
    assert _ray_rms(cam, model, pix) < 1.5 * ideal
    assert flat > 5 * ideal
    scr = stats["screen"]
    for key, true in (("bow_x_mm", 0.5), ("bow_y_mm", 0.3), ("twist_mm", 0.0),
                      ("glass_mm", 1.5)):
        assert abs(scr[key] - true) < 3 * scr["std"][key], key
    assert scr["mode"] == "fit" and scr["glass_index"] == 1.52
    # The flat-equivalent points used for the residual statistics move by the correction.
    moved = np.abs(used[0].screen_px - real_pts[0].subset(
        np.isin(real_pts[0].pixels[:, 0] * 1e4 + real_pts[0].pixels[:, 1],
                used[0].pixels[:, 0] * 1e4 + used[0].pixels[:, 1])).screen_px)
    assert moved.max() > 0.1


def test_bad_screen_options_are_named() -> None:
    """Clear errors for the new options."""
    cam = cameras.mild_pinhole(80, 60)
    pts, _ = _scene(cam, 1, None)
    with pytest.raises(ValueError, match=r"options\.screen"):
        fit_parametric_dense(pts, (80, 60), "opencv5", SCREEN, {"screen": "curved"})
    with pytest.raises(ValueError, match=r"options\.glass_index"):
        fit_parametric_dense(pts, (80, 60), "opencv5", SCREEN, {"screen": "fit",
                                                                 "glass_index": "1.5"})
    with pytest.raises(ValueError, match=r"options\.points"):
        fit_parametric_dense(pts, (80, 60), "opencv5", SCREEN, {"points": "some"})
    with pytest.raises(ValueError, match="needs options"):
        fit_parametric_dense(pts, (80, 60), "opencv5", SCREEN, {"screen": "fit",
                                                                 "points": "sampled"})


@pytest.fixture(scope="module")
def fisheye_seen_by_opencv5():
    """A 150-degree fisheye seen by opencv5 (a model it cannot fit): its points, sample
    pixels, and OpenCV's sampled fit (model, poses)."""
    cam = cameras.wide_fisheye(160, 120, fov_deg=150)
    pts, pix = _scene(cam, 4, None)
    model, found, _, _ = fit_parametric(pts, (160, 120), "opencv5")
    return cam, pts, pix, model, found


def test_a_rejected_trial_leaves_no_trace_in_the_cost(fisheye_seen_by_opencv5) -> None:
    """The unprojection's warm start is part of the state: after a trial step and a restore
    the cost is the same as before the trial (a start left by a trial had made it orders
    of magnitude higher), and a step that makes points unprojectable is not rewarded by a
    smaller sum."""
    _, pts, _, model, found = fisheye_seen_by_opencv5
    prob = _Problem(copy.deepcopy(model), found, pts, ScreenModel(SCREEN),
                    np.ones(model.get_params().size, dtype=bool))
    cost, residuals, hmat, grad = prob.evaluate(True)
    assert np.isfinite(cost)
    snap = prob.params()
    delta = np.linalg.solve(hmat + 1e-8 * np.diag(np.diag(hmat)), -grad)
    for scale in (1.0, 0.1):
        prob.step(scale * delta)
        trial, trial_res, _, _ = prob.evaluate(False)
        lost = any(np.any(np.isnan(t) & np.isfinite(r))
                   for t, r in zip(trial_res, residuals, strict=True))
        assert not lost or trial == np.inf
        prob.restore(snap)
        assert prob.evaluate(False)[0] == pytest.approx(cost, rel=1e-12)


def test_dense_fit_of_a_model_that_cannot_fit_still_improves_on_opencv(
        fisheye_seen_by_opencv5) -> None:
    """Dense LM of an inadequate model moves from OpenCV's start to a smaller ray error and
    stops on its own (before, every trial looked worse and the fit stayed at the start)."""
    cam, pts, pix, start, _ = fisheye_seen_by_opencv5
    model, _, _, stats, _ = fit_parametric_dense(pts, (160, 120), "opencv5", SCREEN)
    assert stats["converged"] and np.isfinite(stats["reduced_chi2"])
    assert _ray_rms(cam, model, pix) < 0.99 * _ray_rms(cam, start, pix)
