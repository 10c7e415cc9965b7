"""Guided sessions against the demo's fixed pose list, on two simulated cameras: does the
predicted worst ray sigma fall as guided poses are added, does it agree with the
calibration report's figure, and how many poses reach a target sigma?

The guided arms call the functions the routes call (not HTTP: 2 x 2 x 10 fits and plans
over HTTP with rendered captures would take far longer on 2 cores, and the numerics are the
same): `starting_poses` with the camera's nominal pinhole (GET starting-poses) for the first
3 poses, then `plan_next_pose` (GET next-pose) and the simulator executes each suggestion;
one arm asks for the whole screen in view (`min_screen_visible` 1), the other lets the
screen reach past the image's edge (`DEFAULT_MIN_VISIBLE`, the route's default).
A capture is `hw_mocks.synthetic.synthetic_maps` (exact screen points plus Gaussian
decoding noise of 0.05 screen px; no pattern rendering). The fixed arm takes the demo's
list (`random_poses(..., seed 7)`). At each pose count both arms are scored as the report
scores a calibration: `calibrate_parametric` (the calibration job's fit) and the worst
predicted ray sigma of its result (`ray_sigma_map`, `worst_ray_sigma`, the one definition
reports and guidance share). "predicted" is guidance's own figure for the same poses (its
`now`); "rise" flags a count where it went up by more than 2 %.

    nice .venv/bin/python benchmarks/guidance.py [--max-poses 12] [--seed 1]
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.fit.classic.calibrate import calibrate_parametric
from calibration.fit.classic.options import ParametricOptions
from calibration.fit.correspondences import point_set
from calibration.guidance import plan_next_pose, session_points
from calibration.guidance_placement import DEFAULT_MIN_VISIBLE
from calibration.guidance_start import nominal_camera, starting_poses
from calibration.shared.maps import DecodedMaps
from calibration.uncertainty import ray_sigma_map, worst_ray_sigma
from hw_mocks.cameras import make_truth_camera
from hw_mocks.poses import random_poses
from hw_mocks.rig import DEFAULT_SCREEN
from hw_mocks.scene import ScreenPose
from hw_mocks.synthetic import synthetic_maps

# (truth camera, image size, model guidance and calibration use, the operator's nominal
# horizontal field of view for the starting set, a fisheye lens)
CAMERAS = (("mild_pinhole", (160, 120), "opencv5", 60.0, False),
           ("wide_fisheye", (320, 240), "fisheye", 150.0, True))
RISE = 1.02
VISIBLE = (1.0, DEFAULT_MIN_VISIBLE)  # the guided arms' least part of the screen in view
PART = f">= {100 * DEFAULT_MIN_VISIBLE:.0f} % (default)"


def report_worst(maps: list[DecodedMaps], model_name: str) -> float:
    """The worst predicted ray sigma (urad) a calibration's report shows for these poses."""
    res = calibrate_parametric(maps, DEFAULT_SCREEN, model_name, options=ParametricOptions())
    rt = [(p.rotation, p.translation) for p in res.poses]
    grid, sigma, _ = ray_sigma_map(res.model, rt, [point_set(m, DEFAULT_SCREEN) for m in maps],
                                   res.stats.get("param_std"))
    return worst_ray_sigma(res.model, grid, sigma) * 1e6


def run_camera(camera: str, size: tuple[int, int], model_name: str, hfov: float,
               fisheye: bool, max_poses: int, seed: int, min_visible: float) -> dict:
    """Per pose count: one guided arm's predicted and report figures, the fixed list's."""
    truth = make_truth_camera(camera, *size)
    screen = DEFAULT_SCREEN
    rng = np.random.default_rng(seed)

    def capture(pose: ScreenPose) -> DecodedMaps:
        return synthetic_maps(truth, pose, screen, sigma_px=0.05, rng=rng)[0]

    start = starting_poses(nominal_camera(size, hfov_deg=hfov, fisheye=fisheye), screen, 3)
    guided = [capture(ScreenPose(p.rotation, p.translation)) for p in start]
    fixed_list = random_poses(truth, screen, max_poses, np.random.default_rng(7))
    fixed = [capture(p) for p in fixed_list[:3]]
    rows, plan_cpu = [], []
    for n in range(3, max_poses + 1):
        t0 = time.process_time()
        sug, _ = plan_next_pose(session_points(guided, screen), size, screen, model_name,
                                min_visible)
        plan_cpu.append(time.process_time() - t0)
        rows.append({"poses": n, "predicted": sug.worst_before_rad * 1e6,
                     "after": sug.worst_after_rad * 1e6, "helps": sug.helps,
                     "valid": guided[-1].valid_count(),
                     "report": report_worst(guided, model_name),
                     "fixed": report_worst(fixed, model_name)})
        if n < max_poses:
            guided.append(capture(ScreenPose(sug.rotation, sug.translation)))
            fixed.append(capture(fixed_list[n]))
    return {"rows": rows, "plan_cpu_s": float(np.mean(plan_cpu))}


def poses_to(values: list[float], target: float) -> str:
    """First pose count (from 3) whose figure is at or below `target`."""
    hit = [3 + i for i, v in enumerate(values) if v <= target]
    return str(hit[0]) if hit else f">{2 + len(values)}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-poses", type=int, default=12)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    print(f"load {os.getloadavg()[0]:.2f}; screen {DEFAULT_SCREEN.width_px}x"
          f"{DEFAULT_SCREEN.height_px} px at {DEFAULT_SCREEN.pitch_mm[0]} mm; worst predicted "
          "ray 1-sigma in urad")
    for camera, size, model, hfov, fisheye in CAMERAS:
        arms = {v: run_camera(camera, size, model, hfov, fisheye, args.max_poses, args.seed, v)
                for v in VISIBLE}
        whole, part = arms[1.0]["rows"], arms[DEFAULT_MIN_VISIBLE]["rows"]
        print(f"\n{camera} {size[0]}x{size[1]} ({model}; starting set planned with a "
              f"{hfov:.0f} deg {'fisheye' if fisheye else 'pinhole'}); planning "
              f"{np.mean([a['plan_cpu_s'] for a in arms.values()]):.1f} CPU s per suggestion")
        print("| poses | fixed list: report | whole screen: predicted | report | "
              f"valid px | {PART}: predicted | report | valid px |")
        print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        prev: dict[float, float] = {}
        for w, p in zip(whole, part, strict=True):
            cells = [f"{w['poses']}", f"{w['fixed']:.3g}"]
            for v, r in ((1.0, w), (DEFAULT_MIN_VISIBLE, p)):
                rise = " (rise)" if v in prev and r["predicted"] > RISE * prev[v] else ""
                agree = "" if abs(r["predicted"] / r["report"] - 1) <= 0.2 else " (differs)"
                cells += [f"{r['predicted']:.3g}{rise}", f"{r['report']:.3g}{agree}",
                          f"{r['valid']}"]
                prev[v] = r["predicted"]
            print("| " + " | ".join(cells) + " |")
        fixed = [r["fixed"] for r in whole]
        for target in (fixed[len(fixed) // 2], fixed[-1]):
            print(f"poses to reach {target:.3g} urad: fixed list {poses_to(fixed, target)}, "
                  f"guided whole screen {poses_to([r['report'] for r in whole], target)}, "
                  f"guided {PART} {poses_to([r['report'] for r in part], target)}")
        for name, rows in (("whole screen", whole), (PART, part)):
            last = rows[-1]
            print(f"last advice, {name}: {'helps' if last['helps'] else 'no pose helps'} "
                  f"({last['predicted']:.3g} -> {last['after']:.3g} urad)")
    usage = resource.getrusage(resource.RUSAGE_SELF)
    print(f"\nwall {time.perf_counter() - wall0:.0f} s, CPU {time.process_time() - cpu0:.0f} s "
          f"(user {usage.ru_utime:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
