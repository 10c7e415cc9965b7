"""Parametric models on cameras none of them fits: how long the dense (every-pixel) fit takes
to find that out, and how close each model gets (ray error against the simulator's truth).

Run: .venv/bin/python benchmarks/inadequate_fit.py [--camera fisheye|noncentral|both]
Prints per camera and model: wall and CPU seconds of `calibrate`, the dense LM's iterations,
whether it converged, the noise-floor ratios (camera px and screen plane) and the verdict
`model_adequate` (every row should say no), the RMS ray-angle error (mrad, after the
best rotation) on every second pixel the poses saw. Data: the test suite's scenes
(hw_mocks: 150-degree equidistant fisheye, 7 poses at 640x480; smooth non-central camera
with local bumps, 8 poses at 320x240; 0.05 px decoding noise, 2 % gross outliers on the
fisheye); BLAS on one thread, as in CI.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.compare import ray_angle_difference
from calibration.fit.dispatch import calibrate
from calibration.fit.registry import PARAMETRIC
from calibration.shared.plan import ScreenGeometry
from hw_mocks import cameras, poses, synthetic

SCREEN = ScreenGeometry(1920, 1080, (0.2745, 0.2745))


def scene(name: str):
    """(camera, maps) of one of the suite's scenes."""
    if name == "fisheye":
        cam = cameras.wide_fisheye(fov_deg=150)
        rng = np.random.default_rng(12)
        found = poses.random_poses(cam, SCREEN, 7, rng)
        return cam, [synthetic.synthetic_maps(cam, p, SCREEN, sigma_px=0.05, rng=rng,
                                              outlier_fraction=0.02)[0] for p in found]
    cam = cameras.smooth_noncentral(320, 240, bumps=True)
    rng = np.random.default_rng(7)
    found = poses.random_poses(cam, SCREEN, 8, rng, distance_mm=(150.0, 450.0))
    return cam, [synthetic.synthetic_maps(cam, p, SCREEN, rng=rng, sigma_px=0.05)[0]
                 for p in found]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--camera", choices=("fisheye", "noncentral", "both"), default="both")
    args = ap.parse_args()
    names = ("fisheye", "noncentral") if args.camera == "both" else (args.camera,)
    print(f"inadequate_fit: every parametric model, dense fit (load {os.getloadavg()[0]:.2f} "
          f"on {os.cpu_count()} CPUs)")
    print(f"{'camera':<11} {'model':<16} {'wall s':>7} {'CPU s':>7} {'LM it':>6} {'conv':>5} "
          f"{'floor x':>8} {'screen x':>8} {'adequate':>8} {'ray mrad':>9}")
    total = 0.0
    for name in names:
        cam, maps = scene(name)
        seen = np.logical_or.reduce([m.mask for m in maps])
        v, u = np.nonzero(seen[::2, ::2])
        pix = np.stack([u * 2, v * 2], axis=1).astype(np.float64)
        for model in PARAMETRIC:
            c0, t0 = time.process_time(), time.perf_counter()
            res = calibrate(maps, SCREEN, model)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            total += wall
            ray = ray_angle_difference(res.model.unproject,
                                       lambda p, cam=cam: cam.rays(p[:, 0], p[:, 1]),
                                       (cam.width, cam.height), pixels=pix)["rms_rad"]
            dense = res.stats.get("dense", {})
            print(f"{name:<11} {model:<16} {wall:7.1f} {cpu:7.1f} "
                  f"{dense.get('iterations', 0):6d} {res.stats.get('converged')!s:>5} "
                  f"{res.stats['noise_floor_ratio']:8.2f} "
                  f"{res.stats['noise_floor_ratio_screen']:8.2f} "
                  f"{'yes' if res.stats['model_adequate'] else 'no':>8} {ray * 1e3:9.3f}",
                  flush=True)
    print(f"inadequate fits: {total:.1f} s wall in all (load {os.getloadavg()[0]:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
