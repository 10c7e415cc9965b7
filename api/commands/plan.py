"""`phasecal plan`: write a pattern plan from a preset, with every choice overridable."""

from __future__ import annotations

import argparse

from acquisition.patterns import PRESETS, build_plan
from api.cli import UserError
from calibration.shared.plan import write_plan


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--screen-width-px", type=int, default=1920, help="screen width in pixels")
    p.add_argument("--screen-height-px", type=int, default=1080, help="screen height in pixels")
    p.add_argument(
        "--pitch-mm", type=float, nargs="+", default=[0.2745], metavar="P",
        help="pixel pitch in mm (one value, or x and y)",
    )
    p.add_argument("--preset", default="default", choices=sorted(PRESETS), help="plan preset")
    p.add_argument("--steps", type=int, help="phase steps per period (overrides the preset)")
    p.add_argument("--axes", default="xy", choices=["x", "y", "xy"], help="axes to code")
    p.add_argument("--periods-x", type=float, nargs="+", help="explicit x periods in screen px")
    p.add_argument("--periods-y", type=float, nargs="+", help="explicit y periods in screen px")
    p.add_argument("--finest-period-px", type=float, help="finest period (overrides preset)")
    p.add_argument("--max-ratio", type=float, help="largest ratio between successive periods")
    p.add_argument("-o", "--output", required=True, help="output plan.json")


def run(args: argparse.Namespace) -> int:
    if len(args.pitch_mm) not in (1, 2):
        raise UserError("--pitch-mm: give one value or two (x y)")
    pitch = args.pitch_mm * 2 if len(args.pitch_mm) == 1 else args.pitch_mm
    plan = build_plan(
        args.screen_width_px,
        args.screen_height_px,
        pitch,
        preset=args.preset,
        axes=tuple(args.axes),
        steps=args.steps,
        periods_x=args.periods_x,
        periods_y=args.periods_y,
        finest_period_px=args.finest_period_px,
        max_ratio=args.max_ratio,
    )
    write_plan(plan, args.output)
    sets = plan.period_sets()
    desc = ", ".join(f"{s.axis}:{s.period_px:g}" for s in sets)
    print(f"wrote {args.output}: {len(plan.frames)} frames, periods [{desc}] px")
    return 0
