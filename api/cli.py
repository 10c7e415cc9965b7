"""`phasecal` command line: one subcommand per module in `api.commands` (docs/formats.md).

Each command module defines `add_arguments(parser)` and `run(args) -> int`; its one-line
help is in `COMMANDS` here.
Errors that are the user's (bad files, bad values) exit 1 with one line on stderr.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from api.version import phasecal_version
from calibration.extras import MissingExtra

#: Every subcommand, in --help order: name -> (module in `api.commands`, one-line help). The
#: help lives here so that `phasecal --help` imports no command: each command's module
#: imports what it needs at its top, and only the command that runs is imported.
COMMANDS: dict[str, tuple[str, str]] = {
    "plan": ("plan", "write a pattern plan (phasecal.plan/1 JSON)"),
    "decode": ("decode", "decode captured frames (FRAMES.npy or a folder of "
                         "frame_NNNN.png/.tif) into maps.npz"),
    "capture": ("capture", "capture one pose on a rig (simulated or a rig .toml/.json) into "
                           "POSE_DIR"),
    "calibrate": ("calibrate", "fit a camera model (opencv5, opencv-rational, fisheye, raygrid, "
                               "sgcc, ...) to maps, or to target observations"),
    "detect": ("detect", "find chessboard / ChArUco corners in images: one observations NPZ "
                         "per image (phasecal.observations/1)"),
    "report": ("report", "calibration report (verdict, downloads, report.html + PNGs and a "
                         "single-file copy) from a model.json and the poses' maps, or from "
                         "a rig model and its cameras' CAMERA/VIEW= files"),
    "diff": ("diff", "difference of two models' rays (after the best rotation) against "
                     "their combined uncertainty: diff.html + maps + diff.json"),
    "guide": ("guide", "pose guidance from maps: starting poses, whether the poses are "
                       "varied enough, the next pose that most lowers the worst ray sigma"),
    "intrinsics": ("intrinsics", "quick intrinsics before decoding: rectangle vanishing points, "
                                 "general-motion self-calibration, or rotation-only "
                                 "self-calibration"),
    "project": ("project", "project camera-frame points.npy (N,3 mm) to pixels.npy (N,2) with a "
                           "model.json"),
    "unproject": ("unproject", "unproject pixels.npy (N,2) to rays.npz (origins, directions) "
                               "with a model.json"),
    "serve": ("serve", "run the REST service (default 127.0.0.1:8000, simulated rig)"),
    "demo": ("demo", "the whole flow on the simulated rig over HTTP: poses, calibrations, "
                     "comparison table"),
    "devices": ("devices", "list simulated, framebuffer, SDL, V4L2, USB (and, if asked, Aravis) "
                           "devices"),
    "check": ("check", "check a rig: latency, exposure, flats, display response"),
    "batch": ("batch", "re-calibrate many sessions / model settings as one job (in-process or "
                       "on Dask)"),
    "export": ("export", "export a model: opencv-yaml, ros, mrcal (.cameramodel), remap (NPZ "
                         "maps), opencv-fit"),
    "handeye": ("handeye", "where the camera sits on (or beside) a robot: hand-eye from robot "
                           "poses and maps or observations (phasecal.handeye/1)"),
    "auto": ("auto", "the closed loop on a rig with a mover: move, capture, refit until a "
                     "target ray sigma (and hand-eye sigma) or the pose budget"),
    "undistort-points": ("undistort_points", "map pixels.npy (N,2) of a model to a virtual "
                                             "pinhole camera (like cv2.undistortPoints)"),
}


class UserError(Exception):
    """An error caused by the user's input: printed as one line, exit status 1."""


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The top-level parser with every subcommand; the arguments of `only` (default: of every
    command), whose module is imported for them."""
    parser = argparse.ArgumentParser(
        prog="phasecal", description="Camera calibration with an active phase-shift target."
    )
    parser.add_argument("--version", action="version",
                        version=f"phasecal {phasecal_version()} (Python {sys.version.split()[0]})")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, text) in COMMANDS.items():
        p = sub.add_parser(name, help=text, description=text)
        if only is None or name == only:
            mod = importlib.import_module(f"api.commands.{module}")
            mod.add_arguments(p)
            p.set_defaults(run=mod.run, exit_without_teardown=getattr(
                mod, "EXIT_WITHOUT_TEARDOWN", False))
    return parser


def chosen_command(argv: list[str]) -> str | None:
    """The subcommand named on a command line (the first word that is one), or None."""
    return next((word for word in argv if word in COMMANDS), None)


def main(argv: list[str] | None = None, *, exit_now: bool = False) -> int:
    """Run one command; with `exit_now` (the console script) a command whose module sets
    `EXIT_WITHOUT_TEARDOWN` ends the process as soon as it returns, see `_exit_now`."""
    words = sys.argv[1:] if argv is None else argv
    args = build_parser(chosen_command(words) or "").parse_args(words)
    try:
        code = int(args.run(args) or 0)
    except (UserError, MissingExtra, FileNotFoundError, ValueError) as exc:  # (PlanError,
        # MapsError and ModelError are ValueErrors)
        print(f"phasecal {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"phasecal {args.command}: interrupted", file=sys.stderr)
        return 130
    if exit_now and getattr(args, "exit_without_teardown", False):
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
