"""`phasecal` command line: one subcommand per module in `api.commands` (docs/formats.md).

Each command module defines `HELP`, `add_arguments(parser)` and `run(args) -> int`.
Errors that are the user's (bad files, bad values) exit 1 with one line on stderr.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
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
        p.set_defaults(_run=mod.run, _exit_without_teardown=getattr(
            mod, "EXIT_WITHOUT_TEARDOWN", False))
    return parser


def main(argv: list[str] | None = None, *, exit_now: bool = False) -> int:
    """Run one command; with `exit_now` (the console script) a command whose module sets
    `EXIT_WITHOUT_TEARDOWN` ends the process as soon as it returns, see `_exit_now`."""
    from calibration.extras import MissingExtra
    from calibration.maps import MapsError
    from calibration.models.base import ModelError
    from calibration.plan import PlanError

    args = build_parser().parse_args(argv)
    try:
        code = int(args._run(args) or 0)
    except (UserError, PlanError, MapsError, ModelError, MissingExtra, FileNotFoundError,
            ValueError) as exc:
        print(f"phasecal {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"phasecal {args.command}: interrupted", file=sys.stderr)
        return 130
    if exit_now and getattr(args, "_exit_without_teardown", False):
        _exit_now(code)
    return code


def _exit_now(code: int) -> None:
    """End the process without the interpreter's teardown: the command's outputs are
    durable (written, fsynced, renamed) when it returns, and destroying the loaded numba
    kernels' machine code takes 0.1-0.5 s more (benchmarks/RESULTS.md, `phasecal decode`).
    Log handlers and the standard streams are flushed first."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(code)


def console() -> int:
    """Entry point of the `phasecal` console script and of `python -m api.cli`."""
    return main(exit_now=True)


if __name__ == "__main__":
    sys.exit(console())
