"""`phasecal guide`: pose guidance from files, as the service's guidance routes give it: a
varied starting set (no pose needed), whether the poses are varied enough, and the next pose
that most lowers the worst predicted ray sigma."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from api.cli import UserError
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
    p.add_argument("--maps", nargs="*", default=[], metavar="MAPS",
                   help="the poses captured so far (maps.npz), in capture order")
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
    text = json.dumps(out, indent=1)
    if args.output:
        with open(args.output, "w") as fh:
            fh.write(text + "\n")
        print(said)
    else:
        print(text)
    return 0

