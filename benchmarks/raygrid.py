"""raygrid benchmark: fit time, accuracy vs truth and vs opencv5, project speed, JSON size.

Usage: .venv/bin/python benchmarks/raygrid.py [--width 640 --height 480] [--poses 5]
Camera: hw_mocks mild_pinhole (inside the opencv5 family), sigma 0.05 screen px.
Prints one row per model: wall time, iterations, chi2/dof, ray RMS error after the best
rotation, the RMS z-score against the predicted per-pixel sigma, and the ratio to opencv5.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small dense solves: threads only contend

import json
import time

import numpy as np

from calibration.compare import ray_angle_difference
from calibration.fit.dispatch import calibrate
from calibration.shared.plan import ScreenGeometry
from hw_mocks import cameras, poses, synthetic


def main() -> None:
    """Fit central and non-central raygrid and opencv5 to the same maps; print a table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--poses", type=int, default=5)
    args = ap.parse_args()
    w, h = args.width, args.height
    screen = ScreenGeometry(1920, 1080, (0.2745, 0.2745))
    cam = cameras.mild_pinhole(w, h)
    rng = np.random.default_rng(5)
    ps = poses.random_poses(cam, screen, args.poses, rng)
    maps = [synthetic.synthetic_maps(cam, p, screen, rng=rng)[0] for p in ps]

    def truth(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return cam.rays(p[:, 0], p[:, 1])

    rows = []
    for name, model, opts in (
        ("opencv5", "opencv5", None),
        ("raygrid", "raygrid", {}),
        ("raygrid-nc", "raygrid", {"central": False}),
    ):
        t0 = time.perf_counter()
        res = calibrate(maps, screen, model, options=opts)
        wall = time.perf_counter() - t0
        diff = ray_angle_difference(res.model.unproject, truth, (w, h), step_px=4.0)
        row = {"name": name, "wall": wall, "iters": res.stats.get("iterations"),
               "chi2": res.stats.get("chi2_dof"), "ray_rms": diff["rms_rad"], "z": np.nan,
               "json_mb": len(json.dumps(res.model.to_dict())) / 1e6, "proj_us": np.nan}
        if model == "raygrid":
            std, _ = res.model.ray_std(diff["pixels"])
            row["z"] = float(np.sqrt(np.nanmean((diff["angle_rad"] / std) ** 2)))
            pix = diff["pixels"] + 0.3
            o, d = res.model.unproject(pix)
            ok = np.all(np.isfinite(d), axis=1)
            t0 = time.perf_counter()
            res.model.project(o[ok] + 500.0 * d[ok])
            row["proj_us"] = 1e6 * (time.perf_counter() - t0) / max(int(ok.sum()), 1)
        rows.append(row)
    base = rows[0]["ray_rms"]
    print(f"{w}x{h}, {args.poses} poses, sigma 0.05 screen px (mild_pinhole)")
    print(f"{'model':<11} {'wall s':>7} {'iters':>5} {'chi2/dof':>8} {'ray rms rad':>11} "
          f"{'z rms':>6} {'x opencv5':>9} {'json MB':>7} {'project us/pt':>13}")
    for r in rows:
        chi2 = "-" if r["chi2"] is None else f"{r['chi2']:.3f}"
        print(f"{r['name']:<11} {r['wall']:7.1f} {r['iters']!s:>5} {chi2:>8} "
              f"{r['ray_rms']:11.3g} {r['z']:6.2f} {r['ray_rms'] / base:9.2f} "
              f"{r['json_mb']:7.2f} {r['proj_us']:13.2f}")


if __name__ == "__main__":
    main()
