"""`phasecal demo`: full simulated acquisition, decoding and calibration (see `api.demo`).

Only the arguments live here; the service stack is imported when the command runs, so
`phasecal --help` stays fast.
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "the whole flow on the simulated rig over HTTP: poses, calibrations, comparison table"
DEFAULT_MODELS = ("opencv-rational", "sgcc")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of `phasecal demo`."""
    p.add_argument("--out", default=None, help="output folder (default: a new temp folder)")
    p.add_argument("--poses", type=int, default=5, help="number of poses (default 5)")
    p.add_argument("--width", type=int, default=640, help="camera width px")
    p.add_argument("--height", type=int, default=480, help="camera height px")
    p.add_argument("--models", nargs="+", default=list(DEFAULT_MODELS),
                   help=f"models to compare (default {' '.join(DEFAULT_MODELS)})")
    p.add_argument("--preset", default="default", help="pattern plan preset")
    p.add_argument("--seed", type=int, default=7, help="seed of the screen poses")


def run(args: argparse.Namespace) -> int:
    """Entry point for `phasecal demo`: 0 when every calibration succeeded."""
    from api.demo import run_demo

    if args.poses < 3:
        raise ValueError(f"--poses {args.poses}: a calibration needs at least 3 poses")
    rows = run_demo(Path(args.out) if args.out else None, poses=args.poses, width=args.width,
                    height=args.height, models=tuple(args.models), preset=args.preset,
                    seed=args.seed)
    return 0 if all(r.status == "succeeded" for r in rows) else 1
