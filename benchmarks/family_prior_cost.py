"""Cost of sgcc's default family prior on the demo's data: CPU seconds per stage, off vs auto.

The demo (`phasecal demo`) calibrates sgcc on a simulated 640x480 150-degree fisheye, 5 poses,
every pixel. This benchmark fits the same kind of maps outside the service: synthetic maps of
the demo rig's camera and screen at the demo's screen poses (seed 7, sigma 0.05 screen px),
or with `--maps DIR` the decoded maps a demo stored (its `data` folder: poses/*/maps.npz and
sessions/*/plan.json). Each mode runs `--repeats` times, alternating (off, auto, off, ...),
in one process; the table gives median CPU seconds (time.process_time, all threads) per
stage, the stages timed by wrapping the sGCC modules' functions here (benchmark only).
`--before` adds the earlier method (every family fitted on every point, no screening
subset): about 100 CPU s more.

    .venv/bin/python benchmarks/family_prior_cost.py [--maps DIR] [--repeats 2] [--before]
"""

from __future__ import annotations

import argparse
import functools
import glob
import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

import calibration.fit.sgcc.calibrate as sgcc_calibrate
import calibration.metrology.family_prior as family_prior
from calibration.fit.dispatch import calibrate
from calibration.shared.maps import DecodedMaps, load_maps
from calibration.shared.plan import ScreenGeometry
from hw_mocks import synthetic
from hw_mocks.poses import random_poses
from hw_mocks.truth import SimulatorTruth

STAGES = {  # label: the functions it times (module, name)
    "spline fits (free + centred)": [(sgcc_calibrate, "_fit")],
    "family choice": [(sgcc_calibrate, "choose_family")],
    "  first fits (subset; before: all)": [(family_prior, "_dense"),
                                           (family_prior, "_rational_from_init")],
    "prior: projector, tangent, precision": [(sgcc_calibrate, "FieldProjector"),
                                             (sgcc_calibrate, "family_tangent"),
                                             (sgcc_calibrate, "deviation_precision")],
    "prior covariance": [(sgcc_calibrate, "prior_covariance")],
}
# api.demo.demo_rig_config(640, 480) (not imported: benchmarks/api.py shadows the package)
DEMO_RIG = {"kind": "simulated", "camera": {"model": "wide_fisheye", "width": 640, "height": 480}}
FIRST = "  first fits (subset; before: all)"
POLISH = "  rest: screen test, polish on all"


def _demo_maps(maps_dir: str | None) -> tuple[list[DecodedMaps], ScreenGeometry]:
    """The demo's decoded maps (from a stored demo) or synthetic maps of the demo rig."""
    if maps_dir:
        root = Path(maps_dir)
        plan = json.loads(next(root.glob("sessions/*/plan.json")).read_text())["screen"]
        screen = ScreenGeometry(plan["width_px"], plan["height_px"], tuple(plan["pitch_mm"]))
        return [load_maps(f) for f in sorted(glob.glob(str(root / "poses/*/maps.npz")))], screen
    truth = SimulatorTruth.from_config(DEMO_RIG)
    cam, screen = truth.camera, truth.screen
    rng = np.random.default_rng(7)
    poses = random_poses(cam, screen, 5, np.random.default_rng(7))  # the demo's screen poses
    return [synthetic.synthetic_maps(cam, p, screen, rng=rng, sigma_px=0.05)[0]
            for p in poses], screen


def _instrument(acc: dict[str, float]) -> None:
    """Wrap each stage's functions to add their CPU seconds to `acc` (this process only)."""
    def wrap(f: Callable, label: str) -> Callable:
        @functools.wraps(f)
        def timed(*args, **kwargs):
            c0 = time.process_time()
            try:
                return f(*args, **kwargs)
            finally:
                acc[label] = acc.get(label, 0.0) + time.process_time() - c0
        return timed

    for label, functions in STAGES.items():
        for module, name in functions:
            setattr(module, name, wrap(getattr(module, name), label))


def main() -> None:
    """Print the per-stage table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--maps", help="a demo's data folder (default: synthetic demo maps)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--before", action="store_true",
                    help="also the earlier method (every family on every point)")
    args = ap.parse_args()
    maps, screen = _demo_maps(args.maps)
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; "
          f"{len(maps)} poses, {sum(int(m.mask.sum()) for m in maps)} valid pixels")
    acc: dict[str, float] = {}
    _instrument(acc)
    modes = ["off", "auto"] + (["before"] if args.before else [])
    rows: dict[str, list[dict[str, float]]] = {m: [] for m in modes}
    verdict: dict[str, dict] = {}
    default_points = family_prior.SCREEN_POINTS
    for _ in range(args.repeats):
        for mode in modes:
            acc.clear()
            family_prior.SCREEN_POINTS = 10**12 if mode == "before" else default_points
            c0, t0 = time.process_time(), time.perf_counter()
            res = calibrate(maps, screen, "sgcc",
                            options={"family_prior": "off" if mode == "off" else "auto"})
            row = {**acc, "total": time.process_time() - c0, "wall": time.perf_counter() - t0}
            row[POLISH] = row.get("family choice", 0.0) - row.get(FIRST, 0.0)
            rows[mode].append(row)
            verdict[mode] = res.stats.get("family_prior") or {}
    family_prior.SCREEN_POINTS = default_points
    labels = [*list(STAGES)[:3], POLISH, *list(STAGES)[3:], "total", "wall"]
    head = f"CPU s (median of {args.repeats})"
    print(f"{head:<40}" + "".join(f"{m:>10}" for m in modes))
    for label in labels:
        name = "wall s (load-dependent)" if label == "wall" else label
        print(f"{name:<40}" + "".join(
            f"{np.median([r.get(label, 0.0) for r in rows[m]]):>10.2f}" for m in modes))
    off = np.median([r["total"] for r in rows["off"]])
    for mode in modes[1:]:
        v = verdict[mode]
        print(f"{mode}: {np.median([r['total'] for r in rows[mode]]) / off:.2f}x off (CPU); "
              f"family {v.get('family')}, gain {v.get('chi2_gain', float('nan')):.1f} "
              f"<= {v.get('chi2_gain_limit', float('nan')):.1f}, tested on {v.get('tested_on')}, "
              f"refused {[(r['family'], r['tested_on']) for r in v.get('refused', [])]}")


if __name__ == "__main__":
    main()
