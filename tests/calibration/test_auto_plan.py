"""Flange-space planning: the starting set steps back (telling the screen's distance) and
turns about non-parallel axes through a point at that distance, a capture that lost the
screen is recognised, and a planned screen pose converts to the flange pose that shows it
(checked against the simulated arm's truth from outside)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from acquisition.mover import RobotPose
from acquisition.patterns import build_plan
from acquisition.rig import parse_rig_config
from calibration.auto_plan import (
    START_STEP_MM,
    START_TURN_DEG,
    covers_screen,
    flange_for_view,
    probe_moves,
    screen_distance_mm,
    starting_moves,
)
from calibration.guidance_placement import screen_centre_mm
from calibration.handeye.rigid import Rigid
from hw_mocks.arm import handeye_rig
from hw_mocks.cameras import mild_pinhole
from hw_mocks.rig import SimulatedRig, open_simulated_rig
from hw_mocks.truth import perfect_maps

PLAN = build_plan(320, 180, 1.0, preset="fast")


def test_starting_turns_keep_the_pivot_and_turn_about_non_parallel_axes() -> None:
    rot = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    t = np.array([500.0, 20.0, 300.0])
    here, back = probe_moves(rot, t)
    assert np.allclose(here.flange.rotation, rot) and np.allclose(here.flange.translation, t)
    assert np.allclose(back.flange.rotation, rot)
    assert np.allclose(back.flange.translation, t + rot @ [0.0, 0.0, START_STEP_MM])
    moves = starting_moves(rot, t, 4, pivot_mm=400.0, distance_mm=400.0)
    pivot = rot @ [0.0, 0.0, 400.0] + t  # the point turned about, in the base frame
    axes = []
    for move in moves:
        relative = Rotation.from_matrix(rot.T @ move.flange.rotation).as_rotvec()
        assert np.degrees(np.linalg.norm(relative)) == pytest.approx(START_TURN_DEG)
        axes.append(relative / np.linalg.norm(relative))
        seen = move.flange.rotation.T @ (pivot - move.flange.translation)  # flange frame
        assert seen[:2] == pytest.approx([0.0, 0.0], abs=1e-9)  # still on the tool axis
        assert 0.8 * 400 < seen[2] < 1.2 * 400  # at a varied distance
    assert len({round(float(m.flange.rotation.T[2] @ (pivot - m.flange.translation)))
                for m in moves}) == 3
    for i in range(len(axes)):
        for j in range(i):
            assert abs(axes[i] @ axes[j]) < 0.95  # hand-eye needs non-parallel rotation axes
    with pytest.raises(ValueError, match="count"):
        starting_moves(rot, t, 0, 400.0, 400.0)


def test_a_step_back_tells_the_screen_distance_and_a_lost_screen_is_seen() -> None:
    config = {"kind": "simulated", "camera": {"width": 96, "height": 72},
              "mover": {"backend": "simulated-arm", "speed_mm_s": 1e6, "speed_deg_s": 1e6,
                        "settle_s": 0.0, "repeatability_mm": 0.0, "repeatability_deg": 0.0}}
    rig = open_simulated_rig(parse_rig_config(config))
    sim = rig.simulated
    assert isinstance(sim, SimulatedRig)
    centre = sim.pose.rotation @ screen_centre_mm(rig.screen) + sim.pose.translation
    before = perfect_maps(sim)
    here, back = probe_moves(rig.mover.current_pose().rotation,
                             rig.mover.current_pose().translation_mm)
    rig.move_to(RobotPose(back.flange.rotation, back.flange.translation))
    after = perfect_maps(sim)
    distance = screen_distance_mm(before, after, rig.screen, START_STEP_MM)
    assert distance == pytest.approx(centre[2], rel=0.05)  # the camera looks along +z
    assert covers_screen(before) and covers_screen(after)
    turned = here.flange @ Rigid(Rotation.from_rotvec([0.0, 1.2, 0.0]).as_matrix(), np.zeros(3))
    rig.move_to(RobotPose(turned.rotation, turned.translation))
    assert not covers_screen(perfect_maps(sim))
    rig.close()


@pytest.mark.parametrize("mount", ["eye-in-hand", "eye-to-hand"])
def test_a_screen_pose_converts_to_the_flange_pose_that_shows_it(mount: str) -> None:
    rng = np.random.default_rng(3)
    rig = handeye_rig(mount, mild_pinhole(160, 120), PLAN.screen, rng, repeatability_mm=0.0,
                      repeatability_deg=0.0, speed_mm_s=1e6, speed_deg_s=1e6, settle_s=0.0)
    x = Rigid(rig.hand_eye.rotation, rig.hand_eye.translation_mm)
    y = Rigid(rig.world_target.rotation, rig.world_target.translation_mm)
    for target in rig.view_plan(3, rng):
        rig.arm.move_to(target, 1.0)
        seen = rig.screen_pose()
        got = flange_for_view(mount, x, y, Rigid(seen.rotation, seen.translation))
        assert np.allclose(got.rotation, target.rotation, atol=1e-9)
        assert np.allclose(got.translation, target.translation_mm, atol=1e-6)
