"""A simulated rig's mover carries the camera (eye-in-hand) or the screen (eye-to-hand): the
screen pose follows every move through the rig's hand-eye truth, starting where the rig put
the screen, and a camera turn about its own axis turns the screen the other way."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from acquisition.mover import RobotPose
from acquisition.rig import parse_rig_config
from hw_mocks.arm import SimulatedArm
from hw_mocks.rig import SimulatedRig, open_simulated_rig
from hw_mocks.truth import SimulatorTruth

CONFIG = {"kind": "simulated", "camera": {"width": 64, "height": 48},
          "mover": {"backend": "simulated-arm", "speed_mm_s": 20000.0, "speed_deg_s": 5000.0,
                    "settle_s": 0.0, "repeatability_mm": 0.0, "repeatability_deg": 0.0}}


def _turn(deg: tuple[float, float, float]) -> RobotPose:
    return RobotPose(Rotation.from_rotvec(np.radians(deg)).as_matrix(), np.zeros(3))


def test_a_configured_arm_carries_the_camera_and_the_truth_is_readable() -> None:
    rig = open_simulated_rig(parse_rig_config(CONFIG))
    sim = rig.simulated
    assert isinstance(sim, SimulatedRig) and sim.handeye is not None
    start = sim.pose
    home = rig.mover.current_pose()
    rig.move_to(home @ RobotPose(np.eye(3), np.array([0.0, 0.0, -20.0])))
    assert sim.pose.translation[2] > start.translation[2] + 15  # backed off: screen further
    rig.move_to(home)
    assert np.allclose(sim.pose.translation, start.translation, atol=1e-6)
    truth = SimulatorTruth.from_config(CONFIG).handeye()
    assert truth.mount == "eye-in-hand"
    assert np.allclose(truth.hand_eye.translation_mm, sim.handeye.hand_eye.translation_mm)
    assert np.allclose(truth.world_target.rotation, sim.handeye.world_target.rotation)
    rig.close()


def test_a_configured_arm_can_carry_the_screen_instead() -> None:
    config = {**CONFIG, "mover": {**CONFIG["mover"], "mount": "eye-to-hand"}}
    rig = open_simulated_rig(parse_rig_config(config))
    sim = rig.simulated
    assert isinstance(sim, SimulatedRig) and sim.handeye is not None
    assert sim.handeye.mount == SimulatorTruth.from_config(config).handeye().mount == "eye-to-hand"
    start = sim.pose
    rig.move_to(rig.mover.current_pose() @ RobotPose(np.eye(3), np.array([0.0, 0.0, 20.0])))
    assert not np.allclose(sim.pose.translation, start.translation)  # the screen moved
    rig.close()
    with pytest.raises(ValueError, match="mount"):
        parse_rig_config({**CONFIG, "mover": {**CONFIG["mover"], "mount": "on-the-wall"}})


@pytest.mark.parametrize("mount", ["eye-in-hand", "eye-to-hand"])
def test_the_screen_pose_follows_the_flange_through_the_hand_eye(mount: str) -> None:
    sim = SimulatedRig.from_config({"kind": "simulated", "camera": {"width": 64, "height": 48}})
    start = sim.pose
    arm = SimulatedArm(speed_mm_s=20000.0, speed_deg_s=5000.0, settle_s=0.0,
                       repeatability_mm=0.0, repeatability_deg=0.0)
    truth = sim.carry_on_mover(arm, mount)  # type: ignore[arg-type]
    flange = _turn((5.0, -4.0, 0.0))
    arm.move_to(flange, 5.0)
    seen = sim.pose
    assert not np.allclose(seen.rotation, start.rotation)
    a = RobotPose(seen.rotation, seen.translation)
    if mount == "eye-in-hand":  # the screen fixed in the base frame: F X A = Y
        assert np.allclose((flange @ truth.hand_eye @ a).translation_mm,
                           truth.world_target.translation_mm, atol=1e-6)
    else:  # the camera fixed in the base frame: X A = F Y
        assert np.allclose((truth.hand_eye @ a).translation_mm,
                           (flange @ truth.world_target).translation_mm, atol=1e-6)
    assert sim.truth()["visible"].mean() > 0.3  # a small turn keeps the screen in view
