"""`phasecal diff`: ray-angle difference map of two models after the best aligning rotation."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from api.cli import UserError
from calibration import load_model_any, write_diff
from calibration.shared.maps import load_maps


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model_a", help="first model (phasecal JSON, mrcal .cameramodel or OpenCV YAML)")
    p.add_argument("model_b", help="second model (same formats)")
    p.add_argument("--maps", nargs="+", default=[],
                   help="compare only pixels these poses' maps decoded (default: every pixel)")
    p.add_argument("--step", type=float, default=4.0, help="grid step in pixels (default 4)")
    p.add_argument("-o", "--output", required=True, help="output folder")


def run(args: argparse.Namespace) -> int:
    if args.step < 1:
        raise UserError(f"--step: expected >= 1 px, got {args.step}")
    a, b = load_model_any(args.model_a), load_model_any(args.model_b)
    pixels = None
    if args.maps:
        step = int(args.step)
        union = np.any([load_maps(m).mask for m in args.maps], axis=0)[::step, ::step]
        v, u = np.nonzero(union)
        pixels = np.stack([u * step, v * step], axis=1).astype(np.float64)
    s = write_diff(a, b, args.output, pixels, float(int(args.step)) if args.maps else args.step,
                   (Path(args.model_a).name, Path(args.model_b).name))
    print(f"wrote {Path(args.output) / 'diff.png'}: RMS {s['rms_urad']:.4g} urad, p95 "
          f"{s['p95_urad']:.4g} urad, max {s['max_urad']:.4g} urad over "
          f"{s['pixels_compared']} pixels")
    return 0
