"""Pattern codes are rendered once per display and reused by later poses."""

from __future__ import annotations

import numpy as np
import pytest

import acquisition.pattern_cache as pc
from acquisition.controller import ControllerOptions, capture_pose
from acquisition.patterns import build_plan, render_frame
from acquisition.sinks import MemoryFrameStore
from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import mild_pinhole
from hw_mocks.rig import SimulatedRig

SCREEN = ScreenGeometry(320, 200, (0.5, 0.5))
PLAN = build_plan(320, 200, 0.5)


@pytest.fixture
def renders(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    calls: list[int] = []

    def counting(plan, index, **kwargs):
        calls.append(index)
        return render_frame(plan, index, **kwargs)

    monkeypatch.setattr(pc, "render_frame", counting)
    return calls


def test_a_second_pose_renders_nothing_and_shows_the_same_codes(renders: list[int]) -> None:
    r = SimulatedRig(mild_pinhole(80, 60), SCREEN, display={"history_s": 1e9})
    opts = ControllerOptions(latency_s=2 / 60)
    first = capture_pose(r.rig, PLAN, MemoryFrameStore(), options=opts)
    assert first.status == "complete" and sorted(set(renders)) == list(range(len(PLAN.frames)))
    assert len(renders) == len(PLAN.frames)  # the integrity repeats were cached too
    renders.clear()
    second = capture_pose(r.rig, PLAN, MemoryFrameStore(), options=opts)
    assert second.status == "complete" and renders == []
    shown = {h.flip_s: h.codes for h in r.display.history()}
    for res in (first, second):
        assert all(np.array_equal(shown[info.flip_s], render_frame(PLAN, i))
                   for i, info in res.frames.items())


def test_random_dither_is_drawn_anew_and_the_byte_cap_holds(renders: list[int]) -> None:
    cache = pc.PatternCache(max_bytes=3 * 320 * 200)  # room for three 8-bit patterns
    digest = PLAN.digest()
    for _ in range(2):
        for i in range(5):
            codes = cache.codes(PLAN, digest, i, bit_depth=8, response=None, dither="ordered")
            assert not codes.flags.writeable and codes.shape == (200, 320)
    assert renders == [0, 1, 2, 3, 4, 3, 4] and cache.nbytes == 3 * 320 * 200
    renders.clear()
    for _ in range(2):
        cache.codes(PLAN, digest, 7, bit_depth=8, response=None, dither="random")
    assert renders == [7, 7]
