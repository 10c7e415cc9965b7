"""`phasecal report`: the calibration report (HTML page + PNGs) from a model and its maps."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from calibration import gather, load_model, write_report
from calibration.shared.maps import load_maps
from calibration.shared.plan import read_plan


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True, help="fitted model (phasecal.model/1 JSON)")
    p.add_argument("--plan", required=True, help="pattern plan (for the screen geometry)")
    p.add_argument("--maps", required=True, nargs="+", help="training poses' maps (.npz)")
    p.add_argument("--heldout-maps", nargs="+", default=[], metavar="NPZ",
                   help="held-out poses' maps, validated with the model")
    p.add_argument("--result", help="the fit's result.json (fitted poses and statistics); "
                                    "without it each pose is located by PnP with the model")
    p.add_argument("--title", default=None, help="page title")
    p.add_argument("-o", "--output", required=True, help="output folder")


def run(args: argparse.Namespace) -> int:
    model = load_model(args.model)
    plan = read_plan(args.plan)
    result = json.loads(Path(args.result).read_text()) if args.result else {}
    maps = [load_maps(m) for m in args.maps]
    held = [load_maps(m) for m in args.heldout_maps]
    labels = [Path(m).stem for m in (*args.maps, *args.heldout_maps)]
    data = gather(model, result, maps, held, plan.screen, labels=labels)
    names = write_report(data, args.output, args.title or f"Calibration report: {args.model}")
    print(f"wrote {Path(args.output) / 'report.html'} and {len(names) - 1} images")
    return 0
