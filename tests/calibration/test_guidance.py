"""Pose guidance against the simulator's truth: the worst predicted ray sigma it plans with
is the calibration's, it falls as guided poses are added, a rational calibration near 0/0
is refitted and no longer reads 1e7 urad, starting poses are varied and recognized once
captured, repeats are named."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.fit.classic.calibrate import calibrate_parametric
from calibration.fit.classic.options import ParametricOptions
from calibration.fit.correspondences import point_set
from calibration.guidance import (
    fit_session,
    plan_next_pose,
    session_points,
    suggest_next_pose,
)
from calibration.guidance_placement import DEFAULT_MIN_VISIBLE, outline_distance
from calibration.guidance_start import nominal_camera, starting_poses
from calibration.guidance_variety import captured_by, observe, pose_variety
from calibration.uncertainty import (
    MIN_POLE_MARGIN,
    radial_pole_margin,
    ray_sigma_map,
    worst_ray_sigma,
)
from hw_mocks.cameras import make_truth_camera
from hw_mocks.poses import random_poses
from hw_mocks.rig import DEFAULT_SCREEN
from hw_mocks.scene import ScreenPose
from hw_mocks.synthetic import synthetic_maps

SIZE = (160, 120)
MIN_POSES = {"opencv5": 3, "sgcc": 6}

# Three poses of `phasecal demo`'s list and the six the planner suggested after them (the
# rational planner before its fix): the weighted opencv-rational fit of all nine lands
# where its radial factor is 0/0 at the image corner; its ray sigma there read 1.07e7 urad
# (the ray itself was right to 133 urad).
_POLE_POSES = (
    ((0.121703, 0.101262, -0.339301), (-63.5804, -4.3657, 112.4065)),
    ((-0.051969, 0.501984, -0.169774), (-49.8545, -14.4973, 170.0388)),
    ((-0.668836, -0.294497, 0.192121), (-78.4741, -58.3848, 153.6895)),
    ((-0.148201, -0.641183, 0.049315), (-117.9691, -17.1013, 215.6344)),
    ((-0.14926, -0.674704, 0.05247), (35.8647, -18.0015, 207.567)),
    ((-0.007785, -0.015038, 5.9e-05), (-81.9522, -48.8029, 137.9008)),
    ((-0.15001, 0.648141, -0.050501), (-171.0853, -2.1669, 308.1751)),
    ((-0.007557, -0.606631, 0.002365), (-31.0854, -48.7381, 145.9873)),
    ((0.283526, -0.013396, -0.001912), (-82.3451, -22.237, 149.5444)),
)


@pytest.fixture(scope="module")
def truth():
    return make_truth_camera("mild_pinhole", *SIZE)


def _maps(truth, poses: list[ScreenPose], seed: int = 1) -> list:
    rng = np.random.default_rng(seed)
    return [synthetic_maps(truth, p, DEFAULT_SCREEN, sigma_px=0.05, rng=rng)[0] for p in poses]


def _pose(rvec, tvec) -> ScreenPose:
    return ScreenPose(cv2.Rodrigues(np.asarray(rvec, float))[0], np.asarray(tvec, float))


def test_a_rational_calibration_near_0_over_0_is_refitted_and_guidance_agrees(truth) -> None:
    """The calibration itself refits a rational fit that lands near 0/0 (its stats say so);
    guidance takes that fit, so both read the same worst sigma, which covers the rays'
    true error and is far from the 1e7 urad the pole read."""
    maps = _maps(truth, [_pose(r, t) for r, t in _POLE_POSES])
    res = calibrate_parametric(maps, DEFAULT_SCREEN, "opencv-rational",
                               options=ParametricOptions())
    note = res.model.stats["fit_note"]
    assert "near 0/0" in note and "refit is kept" in note  # the case reproduces, and is met
    assert radial_pole_margin(res.model) >= MIN_POLE_MARGIN
    points = session_points(maps, DEFAULT_SCREEN)
    grid, sigma, _ = ray_sigma_map(res.model, [(p.rotation, p.translation) for p in res.poses],
                                   points, res.stats["param_std"])
    reported = worst_ray_sigma(res.model, grid, sigma)
    fit = fit_session(points, SIZE, DEFAULT_SCREEN, "opencv-rational")
    assert fit.note == note
    g2, s2, _ = ray_sigma_map(fit.model, fit.poses, fit.points, fit.param_std)
    planned = worst_ray_sigma(fit.model, g2, s2)
    assert planned == pytest.approx(reported, rel=0.2) and 20e-6 < reported < 1e-3
    # the true rays of the calibration: the predicted worst covers its typical error
    _, fitted = res.model.unproject(grid)
    _, true = truth.rays(grid[:, 0], grid[:, 1])
    err = np.arccos(np.clip(np.sum(fitted * true, 1) / np.linalg.norm(fitted, axis=1)
                            / np.linalg.norm(true, axis=1), -1, 1))
    assert np.percentile(err, 50) < 3 * np.median(sigma)


def test_guided_poses_lower_the_worst_sigma_the_calibration_reports(truth) -> None:
    """opencv5 on the small simulated camera: each suggestion lowers the predicted worst
    sigma, the next fit's figure falls, and the figure is the calibration's own (the same
    definition on the calibration's fit of the same poses)."""
    maps = _maps(truth, random_poses(truth, DEFAULT_SCREEN, 3, np.random.default_rng(7)))
    rng = np.random.default_rng(2)
    nows = []
    for _ in range(2):
        sug, _ = plan_next_pose(session_points(maps, DEFAULT_SCREEN), SIZE, DEFAULT_SCREEN,
                                "opencv5")
        assert sug.helps and sug.worst_after_rad < sug.worst_before_rad and sug.note == ""
        assert sug.placement.image_fraction >= 0.08
        nows.append(sug.worst_before_rad)
        maps.append(synthetic_maps(truth, ScreenPose(sug.rotation, sug.translation),
                                   DEFAULT_SCREEN, sigma_px=0.05, rng=rng)[0])
    res = calibrate_parametric(maps, DEFAULT_SCREEN, "opencv5", options=ParametricOptions())
    grid, sigma, _ = ray_sigma_map(res.model, [(p.rotation, p.translation) for p in res.poses],
                                   [point_set(m, DEFAULT_SCREEN) for m in maps],
                                   res.stats["param_std"])
    reported = worst_ray_sigma(res.model, grid, sigma)
    fit = fit_session(session_points(maps, DEFAULT_SCREEN), SIZE, DEFAULT_SCREEN, "opencv5")
    g2, s2, _ = ray_sigma_map(fit.model, fit.poses, fit.points, fit.param_std)
    planned_now = worst_ray_sigma(fit.model, g2, s2)
    assert planned_now == pytest.approx(reported, rel=0.05)
    assert nows[0] > nows[1] > planned_now
    # a screen that may reach past the image's edge has every whole-screen choice and more
    whole = suggest_next_pose(fit, DEFAULT_SCREEN, 1.0)
    part = suggest_next_pose(fit, DEFAULT_SCREEN)  # the default lets it reach past the edge
    assert whole.placement.visible_fraction == 1.0
    assert part.worst_after_rad <= whole.worst_after_rad
    assert part.placement.visible_fraction >= DEFAULT_MIN_VISIBLE


def test_starting_poses_are_varied_and_recognized_once_captured(truth) -> None:
    camera = nominal_camera(SIZE)
    planned = starting_poses(camera, DEFAULT_SCREEN, 5)
    assert len(planned) == 5
    for i, a in enumerate(planned):
        assert a.image_fraction >= 0.08 and np.all(a.outline_px >= 0)
        assert all(outline_distance(a.outline_px, b.outline_px, SIZE) > 0.05
                   for b in planned[i + 1:])
    normals = np.array([p.rotation[:, 2] for p in planned])
    assert np.degrees(np.arccos(np.clip(normals @ normals.T, -1, 1))).max() > 20
    maps = _maps(truth, [ScreenPose(p.rotation, p.translation) for p in planned[:3]])
    k = camera.model.camera_matrix
    seen = [(f"pose_{i}", observe(m, DEFAULT_SCREEN, k)) for i, m in enumerate(maps)]
    assert [captured_by(p, seen, SIZE) for p in planned] == ["pose_0", "pose_1", "pose_2",
                                                              None, None]
    variety = pose_variety(seen, SIZE, MIN_POSES)
    assert variety["ready_for_guidance"] and not variety["duplicates"]
    assert variety["ready_for_calibration"] == {"opencv5": True, "sgcc": False}


def test_repeated_and_parallel_poses_are_named(truth) -> None:
    camera = nominal_camera(SIZE)
    k = camera.model.camera_matrix
    pose = random_poses(truth, DEFAULT_SCREEN, 1, np.random.default_rng(7))[0]
    same = [(f"p{i}", observe(m, DEFAULT_SCREEN, k)) for i, m in enumerate(
        _maps(truth, [pose, pose, pose]))]
    v = pose_variety(same, SIZE, MIN_POSES)
    assert not v["ready_for_guidance"] and not any(v["ready_for_calibration"].values())
    assert [(d["pose_id"], d["repeats"]) for d in v["duplicates"]] == [("p1", "p0"), ("p2", "p0")]
    assert all(d["similarity"] > 0.9 for d in v["duplicates"]) and "repeat" in v["reason"]
    # facing the camera at three places: distinct outlines, parallel screens
    flat = [ScreenPose(np.eye(3), np.array([x, y, 200.0]))
            for x, y in ((-90.0, -55.0), (-60.0, -45.0), (-75.0, -35.0))]
    seen = [(f"f{i}", observe(m, DEFAULT_SCREEN, k)) for i, m in enumerate(_maps(truth, flat))]
    v = pose_variety(seen, SIZE, MIN_POSES)
    assert not v["duplicates"] and not v["ready_for_guidance"] and "tilt" in v["reason"]
