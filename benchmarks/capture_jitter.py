"""Controller pace under a busy machine's delays, on the virtual clock (reproducible).

Run: .venv/bin/python benchmarks/capture_jitter.py
A real-clock capture on a loaded 2-core machine is not reproducible; this models what the
machine does to the capture thread on the simulated rig's virtual clock: every sleep wakes
late by an exponentially distributed delay (mean `jitter`), rendering a pattern's device
codes costs `render` and storing a frame `store` (a 5 Mpixel memory copy on a busy
machine). Default plan (50 frames) + the 3 integrity repeats, 60 Hz, 4 ms exposure,
software trigger, camera readout 5 ms; R = pose time / vsync floor of the 50 plan frames
(benchmarks/acquisition_timing.py), mean of 3 seeds; `recapt` = torn frames shown again.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import acquisition.controller as controller
import acquisition.pattern_cache as pattern_cache
from acquisition.patterns import build_plan
from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import mild_pinhole
from hw_mocks.clock import VirtualClock
from hw_mocks.rig import SimulatedRig

SCREEN = ScreenGeometry(320, 200, (0.5, 0.5))
P, EXPOSURE = 1 / 60, 0.004


class LateClock(VirtualClock):
    """Virtual time whose sleeps end late by an exponential delay of mean `jitter_s`."""

    def __init__(self, jitter_s: float, seed: int) -> None:
        super().__init__()
        self.jitter_s, self.rng = jitter_s, np.random.default_rng(seed)

    def sleep_until(self, t: float) -> None:
        if t > self.now():
            super().sleep_until(t + (self.rng.exponential(self.jitter_s) if self.jitter_s else 0))


class CostlySink:
    """A frame sink whose every store costs `cost_s` of the clock."""

    def __init__(self, clock: VirtualClock, cost_s: float) -> None:
        self.clock, self.cost_s = clock, cost_s

    def add(self, index: int, image: np.ndarray) -> None:
        self.clock.advance(self.cost_s)


def pose(latency: int, jitter_s: float, render_s: float, store_s: float, seed: int
         ) -> tuple[float, int]:
    """(pose time / vsync floor, recaptures) of one modelled capture."""
    clock = LateClock(jitter_s, seed)
    sim = SimulatedRig(mild_pinhole(80, 60), SCREEN, clock=clock,
                       display={"latency_periods": latency, "history_s": 1e9})
    plan = build_plan(SCREEN.width_px, SCREEN.height_px, SCREEN.pitch_mm)
    render = pattern_cache.render_frame

    def costly_render(*args, **kwargs):
        clock.advance(render_s)
        return render(*args, **kwargs)

    pattern_cache.render_frame = costly_render
    try:
        res = controller.capture_pose(
            sim.rig, plan, CostlySink(clock, store_s),
            settings=sim.with_settings(exposure_s=EXPOSURE, trigger_mode="software"),
            options=controller.ControllerOptions(latency_s=latency * P))
    finally:
        pattern_cache.render_frame = render
    if res.status != "complete":
        raise SystemExit(f"capture {res.status}: {res.reason}")
    floor = latency * P + P + len(plan.frames) * math.ceil((P + EXPOSURE) / P - 1e-9) * P
    return res.duration_s / floor, len(res.recaptures)


def main() -> None:
    print(f"{'latency':>7} {'jitter ms':>9} {'render ms':>9} {'store ms':>8} {'R':>6} "
          f"{'recapt':>6}")
    for latency in (1, 2, 3):
        for jitter, render, store in ((0, 3.5, 2), (1, 3.5, 2), (2, 3.5, 7), (4, 3.5, 7)):
            runs = [pose(latency, jitter / 1e3, render / 1e3, store / 1e3, s) for s in range(3)]
            print(f"{latency:7d} {jitter:9.0f} {render:9.1f} {store:8.0f} "
                  f"{np.mean([r for r, _ in runs]):6.3f} {sum(n for _, n in runs):6d}")


if __name__ == "__main__":
    main()
