"""`phasecal` command line: one subcommand per module in `api.commands` (FORMATS.md contract).

Each command module defines `HELP`, `add_arguments(parser)` and `run(args) -> int`.
Errors that are the user's (bad files, bad values) exit 1 with one line on stderr.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from api.version import phasecal_version

# Order shown in --help. A module listed here that does not exist yet is skipped.
COMMANDS = [
    "plan",
    "decode",
    "capture",
    "calibrate",
    "report",
    "diff",
    "intrinsics",
    "project",
    "unproject",
    "serve",
    "demo",
    "devices",
    "check",
    "batch",
    "export",
    "undistort_points",
]


class UserError(Exception):
    """An error caused by the user's input: printed as one line, exit status 1."""


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every available subcommand."""
    parser = argparse.ArgumentParser(
        prog="phasecal", description="Camera calibration with an active phase-shift target."
    )
    parser.add_argument("--version", action="version",
                        version=f"phasecal {phasecal_version()} (Python {sys.version.split()[0]})")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"api.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"api.commands.{name}":
                continue
            raise
        p = sub.add_parser(getattr(mod, "NAME", name), help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `phasecal` console script."""
    from calibration.extras import MissingExtra
    from calibration.maps import MapsError
    from calibration.models.base import ModelError
    from calibration.plan import PlanError

    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except (UserError, PlanError, MapsError, ModelError, MissingExtra, FileNotFoundError,
            ValueError) as exc:
        print(f"phasecal {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"phasecal {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
