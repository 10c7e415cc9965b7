"""Poses needed to reach a target ray sigma: guided (GET /sessions/{id}/next-pose's planner)
against the demo's fixed pose list, on simulated cameras.

Both arms start from the first 3 poses of the fixed list (`random_poses(..., seed 7)`, as
`phasecal demo` uses). The fixed arm then takes the list's next poses; the guided arm asks
`calibration.guidance.plan_next_pose` (which sees only the decoded maps) and the simulator
executes the suggested pose (`hw_mocks.synthetic.synthetic_maps`: exact screen points plus
Gaussian decoding noise of 0.05 screen px; no pattern rendering, to stay quick). After each
pose both arms are scored the same way: a parametric fit to all poses so far and its
predicted worst ray sigma (Fisher information, `calibration.uncertainty`) over the pixels
whose true ray is within 70 degrees of the axis (simulator truth, used for scoring only).

    .venv/bin/python benchmarks/guidance.py [--target-urad 40] [--max-poses 10]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.fit.classic.parametric import fit_parametric
from calibration.guidance import plan_next_pose, session_points
from calibration.uncertainty import free_parameters, parametric_ray_sigma, sensor_grid
from hw_mocks.cameras import make_truth_camera
from hw_mocks.poses import random_poses
from hw_mocks.rig import DEFAULT_SCREEN
from hw_mocks.scene import ScreenPose
from hw_mocks.synthetic import synthetic_maps

CAMERAS = (("wide_fisheye", "opencv-rational"), ("mild_pinhole", "opencv5"))
SIZE = (640, 480)
POINTS = 1000


def worst_sigma(points: list, model_name: str, region: np.ndarray, grid: np.ndarray) -> float:
    """The product's predicted worst ray sigma (urad) of a fit to `points`, over `region`."""
    model, poses, used, stats = fit_parametric(points, SIZE, model_name,
                                               {"max_points_per_pose": POINTS})
    free = free_parameters(model, stats.get("param_std"))
    sig = parametric_ray_sigma(model, [(p.rotation, p.translation) for p in poses], used,
                               grid[region], free)
    return float(np.nanmax(sig)) * 1e6


def run_camera(camera: str, model_name: str, max_poses: int, rng_seed: int) -> dict:
    """Worst-sigma curves of both arms for one simulated camera."""
    truth = make_truth_camera(camera, *SIZE)
    screen = DEFAULT_SCREEN
    fixed = random_poses(truth, screen, max_poses, np.random.default_rng(7))
    grid = sensor_grid(SIZE, 32, 24)
    _, d = truth.rays(grid[:, 0], grid[:, 1])
    region = np.isfinite(d).all(axis=1) & (d[:, 2] >= np.cos(np.radians(70.0)))
    rng = np.random.default_rng(rng_seed)

    def observe(pose: ScreenPose) -> object:
        maps, _ = synthetic_maps(truth, pose, screen, sigma_px=0.05, rng=rng)
        return session_points([maps], screen, POINTS)[0]

    start = [observe(p) for p in fixed[:3]]
    fixed_pts, guided_pts = list(start), list(start)
    curves: dict[str, list[float]] = {"fixed": [], "guided": []}
    plan_s = []
    for n in range(3, max_poses + 1):
        if n > 3:
            fixed_pts.append(observe(fixed[n - 1]))
            t0 = time.perf_counter()
            sug, _ = plan_next_pose(guided_pts, SIZE, screen, model_name, POINTS)
            plan_s.append(time.perf_counter() - t0)
            guided_pts.append(observe(ScreenPose(sug.rotation, sug.translation)))
        curves["fixed"].append(worst_sigma(fixed_pts, model_name, region, grid))
        curves["guided"].append(worst_sigma(guided_pts, model_name, region, grid))
    return {"curves": curves, "plan_s": float(np.mean(plan_s)) if plan_s else 0.0}


def poses_to(curve: list[float], target: float) -> str:
    """First pose count (from 3) at which `curve` is at or below `target`."""
    hit = [3 + i for i, v in enumerate(curve) if v <= target]
    return str(hit[0]) if hit else f">{2 + len(curve)}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--target-urad", type=float, default=40.0)
    ap.add_argument("--max-poses", type=int, default=10)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    print(f"load: {os.getloadavg()[0]:.2f}; target worst ray sigma {args.target_urad} urad; "
          f"{SIZE[0]}x{SIZE[1]} px, screen {DEFAULT_SCREEN.width_px}x{DEFAULT_SCREEN.height_px} "
          f"px at {DEFAULT_SCREEN.pitch_mm[0]} mm")
    for camera, model in CAMERAS:
        out = run_camera(camera, model, args.max_poses, args.seed)
        c = out["curves"]
        print(f"\n{camera} ({model}); planning {out['plan_s']:.1f} s per suggestion")
        print(f"{'poses':>5} {'fixed worst urad':>17} {'guided worst urad':>18}")
        for i, (f, g) in enumerate(zip(c["fixed"], c["guided"], strict=True)):
            print(f"{3 + i:>5} {f:17.3g} {g:18.3g}")
        targets = [args.target_urad] + [c["fixed"][n - 3] for n in (6, 8, args.max_poses)
                                        if 3 <= n <= args.max_poses]
        for target in targets:
            print(f"poses to reach {target:.3g} urad: fixed {poses_to(c['fixed'], target)}, "
                  f"guided {poses_to(c['guided'], target)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
