"""Hand-eye numerics: the classical methods on exact data, the joint refinement against the
simulated arm's truth in both mountings (within its stated sigma), the robot poses input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.handeye.classical import METHODS, chain, classical
from calibration.handeye.pipeline import handeye_from_maps
from calibration.handeye.rigid import Rigid
from calibration.handeye.robot_poses import RobotPoses, RobotPosesError, robot_poses_from_dict
from calibration.shared.plan import ScreenGeometry
from hw_mocks.arm import handeye_rig
from hw_mocks.cameras import mild_pinhole
from hw_mocks.synthetic import synthetic_maps

CAMERA = mild_pinhole(160, 120)
SCREEN = ScreenGeometry(320, 180, (1.0, 1.0))


class _Plan:
    """The part of a plan hand-eye reads: the screen."""

    screen = SCREEN


def _random_rigid(rng: np.random.Generator, scale_mm: float) -> Rigid:
    return Rigid(Rotation.from_rotvec(rng.uniform(-1.5, 1.5, 3)).as_matrix(),
                 rng.uniform(-scale_mm, scale_mm, 3))


@pytest.mark.parametrize("mount", ["eye-in-hand", "eye-to-hand"])
def test_classical_methods_are_exact_on_exact_data(mount: str) -> None:
    rng = np.random.default_rng(3)
    x, y = _random_rigid(rng, 100), _random_rigid(rng, 800)
    flange = [_random_rigid(rng, 500) for _ in range(6)]
    target = [x.inverse() @ chain(mount, f).inverse() @ y for f in flange]  # type: ignore[arg-type]
    for method in METHODS:
        got_x, got_y = classical(method, mount, flange, target)  # type: ignore[arg-type]
        assert np.abs(got_x.minus(x)).max() < 1e-6, method
        assert np.abs(got_y.minus(y)).max() < 1e-5, method


def _simulated(mount: str, seed: int, views: int = 8) -> tuple[dict, RobotPoses, object]:
    rng = np.random.default_rng(seed)
    rig = handeye_rig(mount, CAMERA, SCREEN, rng, speed_mm_s=1e6, speed_deg_s=1e6,  # type: ignore[arg-type]
                      settle_s=0.0)
    maps, poses = {}, {}
    for k, pose in enumerate(rig.view_plan(views, rng)):
        reported = rig.arm.move_to(pose, 1.0)
        maps[f"v{k}"], _ = synthetic_maps(CAMERA, rig.screen_pose(), SCREEN, sigma_px=0.05,
                                          rng=rng, pose_id=f"v{k}")
        poses[f"v{k}"] = Rigid(reported.rotation, reported.translation_mm)
    return maps, RobotPoses(poses, 0.02, 0.005), rig


@pytest.mark.parametrize("mount", ["eye-in-hand", "eye-to-hand"])
def test_joint_hand_eye_recovers_the_simulated_truth_within_its_sigma(mount: str) -> None:
    maps, robot, rig = _simulated(mount, seed=11)
    doc = handeye_from_maps(mount, robot, _Plan(), maps, "opencv5")  # type: ignore[arg-type]
    assert doc["format"] == "phasecal.handeye/1" and doc["mount"] == mount
    for key, truth in (("hand_eye", rig.hand_eye), ("world_target", rig.world_target)):
        got = Rigid(np.array(doc[key]["R"]), np.array(doc[key]["t_mm"]))
        err = got.minus(Rigid(truth.rotation, truth.translation_mm))
        sigma = np.sqrt(np.diag(doc[key]["covariance"]))
        assert np.all(np.abs(err) < 3 * sigma), (key, err / sigma)
        assert np.all(sigma[3:] < 0.1) and np.all(sigma[:3] < 1e-3)  # informative, not vague
    held = doc["heldout"]
    assert len(held["views"]) == len(maps)
    assert 0.2 < held["normalized_mean"] < 3.0
    assert held["rms_mm"] < 3 * held["expected_rms_mm"]
    assert set(doc["stats"]["classical_methods"]) == set(METHODS)


def test_robot_poses_are_validated_with_the_key_named() -> None:
    good = {"format": "phasecal.robot-poses/1", "repeatability": {"mm": 0.02, "deg": 0.005},
            "poses": {"a": {"R": np.eye(3).tolist(), "t_mm": [1, 2, 3]}}}
    assert robot_poses_from_dict(good).poses["a"].translation.tolist() == [1, 2, 3]
    with pytest.raises(RobotPosesError, match="format"):
        robot_poses_from_dict({**good, "format": "phasecal.robot-poses/2"})
    with pytest.raises(RobotPosesError, match=r"poses\.a\.R: not a rotation"):
        robot_poses_from_dict({**good, "poses": {"a": {"R": (2 * np.eye(3)).tolist(),
                                                       "t_mm": [0, 0, 0]}}})
    with pytest.raises(RobotPosesError, match="repeatability"):
        robot_poses_from_dict({**good, "repeatability": {"mm": 0}})


def test_views_without_robot_poses_are_named() -> None:
    maps, robot, _ = _simulated("eye-in-hand", seed=2, views=4)
    partial = RobotPoses({k: v for k, v in robot.poses.items() if k != "v2"}, 0.02, 0.005)
    with pytest.raises(ValueError, match=r"no pose for view.*v2"):
        handeye_from_maps("eye-in-hand", partial, _Plan(), maps, "opencv5")  # type: ignore[arg-type]
