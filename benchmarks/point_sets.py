"""Correspondence extraction: `point_set` (the local 3x3 outlier filter on both axes, then
the kept pixels) per decoded pose, as every calibration and GET next-pose runs it.

Run: .venv/bin/python benchmarks/point_sets.py [--repeats 3]
Prints, per camera size, the best-of-N wall and CPU seconds of `point_set` with and without
outlier rejection, and Mpixel/s; simulated maps with 2 % gross outliers (hw_mocks).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from acquisition.patterns import build_plan
from calibration.fit.correspondences import point_set
from hw_mocks.cameras import mild_pinhole
from hw_mocks.poses import random_poses
from hw_mocks.synthetic import synthetic_maps

SIZES = ((640, 480), (2448, 2048))


def best(fn, repeats: int) -> tuple[float, float]:
    """Best (wall, CPU) seconds of `repeats` calls."""
    runs = []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        runs.append((time.perf_counter() - t, time.process_time() - c))
    return min(runs)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    screen = build_plan(1920, 1080, 0.2745).screen
    print(f"point_set benchmark (load {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs)")
    print(f"{'camera':>10} {'outliers':>9} {'points':>9} {'wall s':>7} {'CPU s':>7} "
          f"{'Mpix/s':>7}")
    for w, h in SIZES:
        cam = mild_pinhole(w, h)
        rng = np.random.default_rng(3)
        pose = random_poses(cam, screen, 1, rng)[0]
        maps = synthetic_maps(cam, pose, screen, sigma_px=0.05, rng=rng,
                              outlier_fraction=0.02)[0]
        for reject in (True, False):
            n = len(point_set(maps, screen, reject_outliers=reject))
            wall, cpu = best(lambda m=maps, r=reject: point_set(m, screen, reject_outliers=r),
                             args.repeats)
            print(f"{w}x{h:<5} {'rejected' if reject else 'kept':>9} {n:9d} {wall:7.3f} "
                  f"{cpu:7.3f} {w * h / 1e6 / wall:7.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
