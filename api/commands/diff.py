"""`phasecal diff`: two models' rays compared after the best aligning rotation, against the
two fits' combined uncertainty: diff.html with its maps, and diff.json."""

from __future__ import annotations

import argparse
from pathlib import Path

from api.cli import UserError
from calibration import DiffInputs, FitFiles, draw_diff


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model_a", help="first model (phasecal JSON, mrcal .cameramodel or OpenCV YAML)")
    p.add_argument("model_b", help="second model (same formats)")
    p.add_argument("--maps", nargs="+", default=[],
                   help="compare only pixels these poses' maps decoded (default: every pixel); "
                        "also each fit's training maps unless --maps-a/--maps-b are given")
    p.add_argument("--plan", help="the pattern plan of the fits (screen geometry): needed for "
                                  "the uncertainty of a parametric model")
    for side in ("a", "b"):
        p.add_argument(f"--result-{side}", metavar="JSON",
                       help=f"model {side.upper()}'s result.json (default: result.json beside "
                            "the model, if there is one)")
        p.add_argument(f"--maps-{side}", nargs="+", default=None, metavar="NPZ",
                       help=f"model {side.upper()}'s training maps, in its fit's order")
    p.add_argument("--step", type=float, default=4.0, help="grid step in pixels (default 4)")
    p.add_argument("-o", "--output", required=True, help="output folder")


def _fit(model: str, result: str | None, maps: list[str] | None,
         args: argparse.Namespace) -> FitFiles | None:
    """A model's fit files for its uncertainty, or None when they are not all given."""
    beside = Path(model).with_name("result.json")
    path = result or (str(beside) if beside.is_file() else None)
    maps = maps or args.maps
    if result and not args.plan:
        raise UserError("--plan: needed with --result-a/--result-b (the screen geometry)")
    if path is None or not maps or not args.plan:
        return None
    return FitFiles(path, args.plan, list(maps))


def run(args: argparse.Namespace) -> int:
    if args.step < 1:
        raise UserError(f"--step: expected >= 1 px, got {args.step}")
    fits = (_fit(args.model_a, args.result_a, args.maps_a, args),
            _fit(args.model_b, args.result_b, args.maps_b, args))
    s = draw_diff(DiffInputs(args.model_a, args.model_b,
                             (Path(args.model_a).name, Path(args.model_b).name), args.output,
                             list(args.maps), args.step, fits))
    beyond = s["fraction_beyond_2_sigma"]
    print(f"wrote {Path(args.output) / 'diff.html'}: median {s['median_urad']:.4g} urad, p95 "
          f"{s['p95_urad']:.4g} urad, max {s['max_urad']:.4g} urad over "
          f"{s['pixels_compared']} pixels"
          + ("" if beyond is None else f"; {beyond:.1%} beyond 2 combined sigma")
          + f"\n{s['verdict']}")
    return 0
