"""`phasecal handeye`: where the camera sits on (or beside) a robot, from the robot's poses and
the camera's views of a screen or board (phasecal.handeye/1, docs/robots.md)."""

from __future__ import annotations

import argparse

from api.cli import UserError
from api.commands.calibrate import parse_options
from api.progress import progress_bar
from calibration import MODEL_NAMES, MOUNTS, DegenerateError, handeye_files
from calibration.shared.atomic import write_json_atomic


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mount", required=True, choices=MOUNTS,
                   help="eye-in-hand: camera on the flange, target fixed; eye-to-hand: camera "
                        "fixed, target (screen or board) on the flange")
    p.add_argument("--robot-poses", required=True, metavar="ROBOT.json",
                   help="the flange pose of each view as the robot reported it and the robot's "
                        "repeatability (phasecal.robot-poses/1)")
    p.add_argument("--plan", help="pattern plan (phasecal.plan/1; needed with --maps)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--maps", nargs="+", metavar="VIEW=PATH", help="decoded maps, one per view")
    src.add_argument("--observations", nargs="+", metavar="VIEW=PATH",
                     help="target observations (phasecal.observations/1), one per view")
    p.add_argument("--model", required=True, help="camera model fitted first, e.g. opencv5")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="camera model option, VALUE as JSON (as for `phasecal calibrate`)")
    p.add_argument("-o", "--output", required=True, help="output handeye.json")


def view_paths(pairs: list[str], flag: str) -> dict[str, str]:
    """VIEW=PATH arguments as {VIEW: PATH}; UserError for a missing '=' or a repeated VIEW."""
    out: dict[str, str] = {}
    for pair in pairs:
        view, sep, path = pair.partition("=")
        if not sep or not view or not path:
            raise UserError(f"{flag}: expected VIEW=PATH (VIEW as in the robot poses), got "
                            f"{pair!r}")
        if view in out:
            raise UserError(f"{flag}: view {view!r} given twice")
        out[view] = path
    return out


def run(args: argparse.Namespace) -> int:
    """Fit the camera, then the hand-eye; print the result and its checks, write the JSON."""
    if args.model not in MODEL_NAMES:
        raise UserError(f"--model: expected one of {', '.join(MODEL_NAMES)}, got {args.model!r}")
    source = "maps" if args.maps else "observations"
    paths = view_paths(args.maps or args.observations, f"--{source}")
    if source == "maps" and not args.plan:
        raise UserError("--plan: decoded maps need the pattern plan they were decoded with")
    try:
        with progress_bar(f"handeye {args.mount}") as update:
            doc = handeye_files(args.mount, args.robot_poses, source, paths, args.model,
                                plan_path=args.plan, options=parse_options(args.option) or None,
                                progress=update)
    except DegenerateError as exc:
        raise UserError(f"camera calibration failed: {exc}") from None
    write_json_atomic(args.output, doc)
    st, held = doc["stats"], doc["heldout"]
    he, wt = st["hand_eye_sigma"], st["world_target_sigma"]
    print(f"wrote {args.output}: {args.mount}, {len(st['views'])} views, {st['method']}")
    print(f"  hand-eye t_mm {[round(v, 3) for v in doc['hand_eye']['t_mm']]}, 1-sigma "
          f"{he['translation_mm']:.3g} mm, {he['rotation_mrad']:.3g} mrad")
    print(f"  world-target 1-sigma {wt['translation_mm']:.3g} mm, {wt['rotation_mrad']:.3g} mrad;"
          f" chi2/dof {st['chi2_per_dof']:.3g}")
    print(f"  held out: RMS {held['rms_mm']:.3g} mm, {held['rms_deg']:.3g} deg (expected "
          f"{held['expected_rms_mm']:.3g} mm, {held['expected_rms_deg']:.3g} deg; normalized "
          f"{held['normalized_mean']:.3g})")
    return 0
