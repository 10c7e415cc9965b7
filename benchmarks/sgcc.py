"""sGCC fit benchmark (seed 000 setup): W x H pixels, 3 poses, default 10x10 mesh, to convergence.

Usage: .venv/bin/python benchmarks/sgcc.py [--size 1024] [--model sgcc-noncentral] [--sigma-px 0.05]
Prints wall time, iterations, final cost and the ratio to seed 000's reported 20 minutes.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small dense solves: threads only contend

import time

import numpy as np

from calibration.compare import in_gauge, sgcc_gauge_transform
from calibration.fit.generic import calibrate_generic
from calibration.models.sgcc import logmap
from calibration.plan import ScreenGeometry
from hw_mocks import cameras, poses, synthetic

SEED000_SECONDS = 20 * 60.0


def main() -> None:
    """Run one full fit and print a one-row table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", type=int, default=1024, help="image width = height, pixels")
    ap.add_argument("--model", default="sgcc-noncentral", choices=["sgcc", "sgcc-noncentral"])
    ap.add_argument("--sigma-px", type=float, default=0.05, help="decoding noise, screen px")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    cam = cameras.smooth_noncentral(args.size, args.size)
    screen = ScreenGeometry(1920, 1080, (0.2745, 0.2745))
    ps = poses.random_poses(cam, screen, 3, rng)
    maps = [
        synthetic.synthetic_maps(cam, p, screen, sigma_px=args.sigma_px, rng=rng)[0] for p in ps
    ]
    t0 = time.perf_counter()
    res = calibrate_generic(maps, screen, args.model)
    wall = time.perf_counter() - t0
    central = args.model == "sgcc"
    q, t = sgcc_gauge_transform(
        lambda p: cam.rays(p[:, 0], p[:, 1]), (args.size, args.size), central
    )
    g = np.linspace(8, args.size - 8, 40)
    pix = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    o, d = in_gauge(lambda p: cam.rays(p[:, 0], p[:, 1]), q, t)(pix)
    (comps,) = res.model.components(pix)
    dir_err = float(np.sqrt(np.mean(np.sum((comps[:, :2] - logmap(d)) ** 2, axis=1))))
    org_err = (
        float(np.sqrt(np.mean(np.sum((comps[:, 2:] - o[:, :2]) ** 2, axis=1))))
        if not central
        else 0.0
    )
    n_px = sum(m.valid_count() for m in maps)
    print(
        "| model | image | valid px | iterations | wall s | final cost | chi2/dof "
        "| ratio to 20 min | dir err rad | origin err mm |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    print(
        f"| {args.model} | {args.size}x{args.size} | {n_px} | {res.stats['iterations']} "
        f"| {wall:.2f} "
        f"| {res.stats['cost']:.6g} | {res.stats['chi2_dof']:.4f} | {wall / SEED000_SECONDS:.4f} "
        f"| {dir_err:.3g} | {org_err:.3g} |"
    )


if __name__ == "__main__":
    main()
