"""`phasecal guide`: pose guidance from files, as the service's guidance routes give it: a
varied starting set (no pose needed), whether the poses are varied enough, and the next pose
that most lowers the worst predicted ray sigma; with `CAMERA/VIEW=PATH` maps (as `phasecal
calibrate` takes a rig's), the next pose of a rig, with a picture per camera under
`--png-dir`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from api.cli import UserError
from api.commands.calibrate_rig import rig_requested, split_prefix
from api.worker.rig_tasks import plan_rig_files, write_rig_pictures
from calibration import (
    DEFAULT_MIN_VISIBLE,
    MODELS,
    PARAMETRIC,
    captured_by,
    guidance_png,
    nominal_camera,
    observe,
    plan_next_pose,
    pose_variety,
    session_points,
    starting_poses,
)
from calibration.shared.maps import load_maps
from calibration.shared.plan import read_plan


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plan", required=True, help="the pattern plan (its screen geometry)")
    p.add_argument("--maps", nargs="*", default=[], metavar="[CAMERA/VIEW=]MAPS",
                   help="the poses captured so far (maps.npz), in capture order; a rig's as "
                        "CAMERA/VIEW=PATH (views named alike are one screen pose)")
    p.add_argument("--model", default="opencv-rational", choices=list(PARAMETRIC),
                   help="the parametric model the prediction uses")
    p.add_argument("--starting", type=int, metavar="N",
                   help="plan N starting poses from the nominal lens (1..12) instead of the "
                        "next pose")
    p.add_argument("--image-size", metavar="WxH",
                   help="the camera's image size (default: the maps'), needed with --starting "
                        "and no maps")
    p.add_argument("--hfov-deg", type=float,
                   help="the nominal lens's horizontal field of view (default 60)")
    p.add_argument("--lens", choices=["pinhole", "fisheye"], default="pinhole",
                   help="the nominal lens of --starting and of the variety check")
    p.add_argument("--min-screen-visible", type=float, default=DEFAULT_MIN_VISIBLE,
                   help="the least part of the suggested screen inside the image (0.5..1; "
                        f"default {DEFAULT_MIN_VISIBLE:g}, as the service's)")
    p.add_argument("-o", "--output", help="write the answer as JSON (default: stdout)")
    p.add_argument("--image", metavar="PNG", help="also draw the next-pose picture")
    p.add_argument("--reference", metavar="CAMERA",
                   help="rig: the camera whose frame the screen pose is in (default: the "
                        "first given)")
    p.add_argument("--png-dir", metavar="DIR",
                   help="rig: also draw a picture per camera (next-pose-CAMERA.png)")


def _size(args: argparse.Namespace, maps: list[Any]) -> tuple[int, int]:
    if args.image_size:
        try:
            w, h = (int(v) for v in args.image_size.lower().split("x"))
        except ValueError:
            raise UserError(f"--image-size: expected WxH, e.g. 1920x1080, got "
                            f"{args.image_size!r}") from None
        if w <= 0 or h <= 0:
            raise UserError(f"--image-size: expected positive pixels, got {args.image_size}")
        return w, h
    if not maps:
        raise UserError("--image-size: required with --starting when no --maps are given")
    h, w = maps[0].shape
    return w, h


def run(args: argparse.Namespace) -> int:
    if rig_requested(args):
        return _run_rig(args)
    if args.png_dir or args.reference:
        raise UserError(f"--{'png-dir' if args.png_dir else 'reference'}: applies to a rig's "
                        "CAMERA/VIEW=PATH maps; one camera's picture is --image PNG")
    plan = read_plan(args.plan)
    maps = [load_maps(m) for m in args.maps]
    size = _size(args, maps)
    camera = nominal_camera(size, hfov_deg=args.hfov_deg, fisheye=args.lens == "fisheye")
    seen = []
    for path, m in zip(args.maps, maps, strict=True):
        try:
            seen.append((path, observe(m, plan.screen, camera.model.camera_matrix)))
        except ValueError as exc:
            print(f"phasecal guide: {path}: {exc}", file=sys.stderr)
    out: dict[str, Any] = {"pose_variety": pose_variety(
        seen, size, {name: spec.min_poses for name, spec in MODELS.items()})}
    if args.starting is not None:
        planned = starting_poses(camera, plan.screen, args.starting)
        out["starting_poses"] = {"camera": camera.to_json(), "poses": [
            {**p.to_json(size), "captured_by": captured_by(p, seen, size)} for p in planned]}
        said = f"{len(planned)} starting poses"
    elif out["pose_variety"]["ready_for_guidance"]:
        sug, _ = plan_next_pose(session_points(maps, plan.screen), size, plan.screen,
                                args.model, args.min_screen_visible)
        out["next_pose"] = sug.to_json()
        said = f"next pose: {sug.placement.words(size)}; {sug.advice}"
        if args.image:
            guidance_png(sug.map_before, sug.map_after, sug.placement.border_px, size,
                         f"next pose ({args.model}): {sug.placement.words(size)}", args.image)
    else:
        raise UserError(f"--maps: no next pose yet: {out['pose_variety']['reason']}")
    _answer(args, out, said)
    return 0


def _run_rig(args: argparse.Namespace) -> int:
    """The next pose of a rig from CAMERA/VIEW=PATH maps, and a picture per camera."""
    for flag, why in (("starting", "plans from one camera's nominal lens"),
                      ("image", "one camera's picture; a rig draws one per camera: --png-dir "
                                "DIR"),
                      ("image_size", "a rig's image sizes are its maps'")):
        if getattr(args, flag) is not None:
            raise UserError(f"--{flag.replace('_', '-')}: not for a rig: {why}")
    maps: dict[str, dict[str, str]] = {}
    for text in args.maps:
        camera, view, path = split_prefix(text) or ("", "", "")
        if view in maps.setdefault(camera, {}):
            raise UserError(f"--maps: {camera}/{view} given twice")
        maps[camera][view] = path
    reference = args.reference or next(iter(maps))
    if reference not in maps:
        raise UserError(f"--reference: {reference!r} is none of the cameras given "
                        f"({', '.join(maps)})")
    ordered = {reference: maps[reference], **maps}
    try:
        sug = plan_rig_files(args.plan, ordered, reference, args.model,
                             args.min_screen_visible)
    except ValueError as exc:
        raise UserError(f"--maps: {exc}") from None
    out = {"next_pose": {"reference": reference, **sug.to_json()}}
    if args.png_dir:
        folder = Path(args.png_dir)
        folder.mkdir(parents=True, exist_ok=True)
        written = write_rig_pictures(sug, args.model, folder)
        for cam in out["next_pose"]["cameras"]:
            cam["image"] = str(written[cam["camera"]])
    _answer(args, out, f"next pose of the rig: serves {', '.join(sug.served)}; {sug.advice}")
    return 0


def _answer(args: argparse.Namespace, out: dict[str, Any], said: str) -> None:
    """The JSON to --output (and `said` on stdout) or to stdout."""
    text = json.dumps(out, indent=1)
    if args.output:
        with open(args.output, "w") as fh:
            fh.write(text + "\n")
        print(said)
    else:
        print(text)
