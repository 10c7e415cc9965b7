"""Time per pose of the acquisition controller against the timing floor (simulated 60 Hz rig).

Floor (docs/physics.md section 7), per pose of N patterns, display period P, exposure e,
latency L, camera frame period T (free-running):
  continuous floor  = L + P + N * (P + e)                      (ignores that flips wait for vsyncs)
  vsync floor       = L + P + N * max(ceil((P + e) / P) * P, T_fr)   with T_fr = T for a
                      free-running camera (one frame per pattern at most), else 0
Flips happen only at vsyncs, so the vsync floor is the real lower bound. The free-running
time depends on the camera's frame phase against the vsyncs: it is averaged over phases.
Virtual clock: only the simulated timing is measured. Run:
  .venv/bin/python benchmarks/acquisition_timing.py
(Named so it does not shadow the `acquisition` package for scripts run from benchmarks/.)
"""

from __future__ import annotations

import math
import time

import numpy as np

from acquisition.controller import ControllerOptions, capture_pose
from acquisition.patterns import build_plan
from acquisition.sinks import MemoryFrameStore
from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import mild_pinhole
from hw_mocks.rig import SimulatedRig

SCREEN = ScreenGeometry(320, 200, (0.5, 0.5))
REFRESH = 60.0
FPS = 30.0


def one_pose(mode: str, exposure: float, latency: int, phase: float) -> float:
    """Clock seconds to capture the default plan once (no integrity repeat)."""
    rig = SimulatedRig(mild_pinhole(80, 60), SCREEN,
                       display={"latency_periods": latency, "refresh_hz": REFRESH})
    plan = build_plan(SCREEN.width_px, SCREEN.height_px, SCREEN.pitch_mm)
    rig.clock.sleep_until(phase)
    s = rig.with_settings(exposure_s=exposure, trigger_mode=mode,
                          frame_rate_hz=FPS if mode == "free-running" else None)
    res = capture_pose(rig.rig, plan, MemoryFrameStore(), settings=s,
                       options=ControllerOptions(latency_s=latency / REFRESH, integrity=False))
    assert res.status == "complete", res.reason
    return res.duration_s


def main() -> None:
    """Print the table."""
    plan = build_plan(SCREEN.width_px, SCREEN.height_px, SCREEN.pitch_mm)
    n, p = len(plan.frames), 1.0 / REFRESH
    print(f"default plan: {n} patterns, display {REFRESH:.0f} Hz, "
          f"free-running camera {FPS:.0f} fps")
    print(f"{'mode':<13}{'exp ms':>7}{'lat':>4}{'pose s':>8}{'cont.floor':>11}{'vsync floor':>12}"
          f"{'ratio c':>8}{'ratio v':>8}{'wall s':>8}")
    for mode in ("software", "free-running"):
        for exposure in (0.005, 0.012):
            for latency in (1, 3):
                phases = [0.0] if mode == "software" else list(np.arange(4) / 4 / FPS + 1e-4)
                t0 = time.perf_counter()
                pose = float(np.mean([one_pose(mode, exposure, latency, ph) for ph in phases]))
                wall = (time.perf_counter() - t0) / len(phases)
                fill = latency * p + p
                cont = fill + n * (p + exposure)
                per = math.ceil((p + exposure) / p - 1e-9) * p
                if mode == "free-running":
                    per = max(per, 1.0 / FPS)
                vs = fill + n * per
                print(f"{mode:<13}{exposure * 1e3:>7.1f}{latency:>4}{pose:>8.3f}{cont:>11.3f}"
                      f"{vs:>12.3f}{pose / cont:>8.2f}{pose / vs:>8.2f}{wall:>8.2f}")


if __name__ == "__main__":
    main()
