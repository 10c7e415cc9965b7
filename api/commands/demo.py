"""`phasecal demo`: full simulated acquisition, decoding and calibration (see `api.demo`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from api.cli import UserError
from api.commands.calibrate import parse_options
from api.demo import demo_rig_config, run_demo
from api.rigs import load_default_config
from calibration import model_spec

DEFAULT_MODELS = ("opencv-rational", "sgcc")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of `phasecal demo`."""
    p.add_argument("--out", default=None, help="output folder (default: a new temp folder)")
    p.add_argument("--poses", type=int, default=5, help="number of poses (default 5)")
    p.add_argument("--width", type=int, default=None, help="camera width px (default 640)")
    p.add_argument("--height", type=int, default=None, help="camera height px (default 480)")
    p.add_argument("--rig", metavar="FILE", default=None,
                   help="a simulated rig config (TOML/JSON, e.g. docs/rigs/"
                        "simulated-bowed-glass.toml) instead of the built-in wide-angle rig")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="model option for every calibration, VALUE as JSON (e.g. "
                        'screen="fit"); repeatable')
    p.add_argument("--models", nargs="+", default=list(DEFAULT_MODELS),
                   help=f"models to compare (default {' '.join(DEFAULT_MODELS)})")
    p.add_argument("--preset", default="default", help="pattern plan preset")
    p.add_argument("--seed", type=int, default=7, help="seed of the screen poses")


def run(args: argparse.Namespace) -> int:
    """Entry point for `phasecal demo`: 0 when every calibration succeeded."""
    if args.poses < 3:
        raise ValueError(f"--poses {args.poses}: a calibration needs at least 3 poses")
    if args.rig is None:
        rig = demo_rig_config(args.width or 640, args.height or 480)
    elif args.width or args.height:
        raise UserError("--width/--height: the camera size comes from the --rig file")
    else:
        rig = load_default_config(args.rig)
        if rig.get("kind") != "simulated":
            raise UserError(f"--rig {args.rig}: the demo needs a simulated rig "
                            f"(kind = \"simulated\"), got {rig.get('kind')!r}")
    options = parse_options(args.option) or None
    for model in args.models:  # before any capture: a typo fails now, not after the poses
        try:
            model_spec(model).parse_options(options)
        except ValueError as exc:
            raise UserError(f"--models/--option: {exc}") from None
    rows = run_demo(Path(args.out) if args.out else None, poses=args.poses, rig=rig,
                    models=tuple(args.models), preset=args.preset, seed=args.seed,
                    options=options)
    return 0 if all(r.status == "succeeded" for r in rows) else 1
