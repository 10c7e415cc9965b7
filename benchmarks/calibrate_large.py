"""A lab-sized calibration: the default (dense, every-pixel) parametric fit and the next-pose
plan on several 2448x2048 (5 MP) poses, as `POST /sessions/{id}/calibrations` and
`GET /sessions/{id}/next-pose` run them in a worker.

Run: .venv/bin/python benchmarks/calibrate_large.py [--poses 4] [--model opencv5]
     [--size 2448 2048]
Prints each stage of the fit as the progress callback reports it (cumulative CPU and wall
seconds), the fit's total, then the next-pose plan's. Simulated maps (hw_mocks: exact
screen points plus 0.05 px Gaussian decoding noise); BLAS on one thread, as in CI.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from acquisition.patterns import build_plan
from api.worker.guidance_task import guidance_task
from calibration.pipeline import calibrate_files
from calibration.shared.maps import save_maps
from calibration.shared.plan import write_plan
from hw_mocks.cameras import mild_pinhole
from hw_mocks.poses import random_poses
from hw_mocks.synthetic import synthetic_maps


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=4)
    ap.add_argument("--model", default="opencv5")
    ap.add_argument("--size", type=int, nargs=2, default=(2448, 2048), metavar=("W", "H"))
    args = ap.parse_args()
    plan = build_plan(1920, 1080, 0.2745)
    cam = mild_pinhole(*args.size)
    rng = np.random.default_rng(1)
    with tempfile.TemporaryDirectory(prefix="phasecal-cal-") as tmp:
        write_plan(plan, f"{tmp}/plan.json")
        paths = []
        for k, pose in enumerate(random_poses(cam, plan.screen, args.poses, rng)):
            maps = synthetic_maps(cam, pose, plan.screen, sigma_px=0.05, rng=rng)[0]
            save_maps(maps, f"{tmp}/pose{k}.npz")
            paths.append(f"{tmp}/pose{k}.npz")
        print(f"calibrate_large: {args.model}, {args.poses} poses of {args.size[0]}x"
              f"{args.size[1]} (load {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs)")
        print(f"{'CPU s':>7} {'wall s':>7}  stage")
        c0, t0 = time.process_time(), time.perf_counter()

        def stage(_i: int, _n: int, msg: str) -> None:
            print(f"{time.process_time() - c0:7.1f} {time.perf_counter() - t0:7.1f}  {msg}",
                  flush=True)

        calibrate_files(f"{tmp}/plan.json", paths, args.model, progress=stage)
        fit_cpu, fit_wall = time.process_time() - c0, time.perf_counter() - t0
        c1, t1 = time.process_time(), time.perf_counter()
        guidance_task(f"{tmp}/plan.json", paths, args.model, tmp, {})
        print(f"fit: {fit_wall:.1f} s wall, {fit_cpu:.1f} CPU s; next-pose plan: "
              f"{time.perf_counter() - t1:.1f} s wall, {time.process_time() - c1:.1f} CPU s "
              f"(load {os.getloadavg()[0]:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
