"""Flange-space planning: starting moves turn about non-parallel axes around the current
pose, and a planned screen pose converts to the flange pose that shows it (checked against
the simulated arm's truth from outside)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from acquisition.patterns import build_plan
from calibration.auto_plan import flange_for_view, starting_moves
from calibration.handeye.rigid import Rigid
from hw_mocks.arm import handeye_rig
from hw_mocks.cameras import mild_pinhole

PLAN = build_plan(320, 180, 1.0, preset="fast")


def test_starting_moves_turn_about_non_parallel_axes() -> None:
    rot = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    t = np.array([500.0, 20.0, 300.0])
    moves = starting_moves(rot, t, 4)
    assert len(moves) == 4
    first = moves[0].flange
    assert np.allclose(first.rotation, rot) and np.allclose(first.translation, t)
    axes = []
    for move in moves[1:]:
        relative = Rotation.from_matrix(rot.T @ move.flange.rotation).as_rotvec()
        assert np.degrees(np.linalg.norm(relative)) == pytest.approx(8.0)
        assert np.linalg.norm(move.flange.translation - t) < 20.0
        axes.append(relative / np.linalg.norm(relative))
    for i in range(len(axes)):
        for j in range(i):
            assert abs(axes[i] @ axes[j]) < 0.9  # hand-eye needs non-parallel rotation axes
    with pytest.raises(ValueError, match="count"):
        starting_moves(rot, t, 0)


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
