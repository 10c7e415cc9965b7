"""`phasecal export`: a model to OpenCV YAML, ROS camera_info, mrcal, remap maps or opencv-fit;
a rig's camera to any of those, a rig's camera pair to opencv-stereo or stereo-remap, and its
cameras' poses to ROS transforms."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from api.cli import UserError
from calibration import (
    RIG_FORMATS,
    ExportOptions,
    export_model,
    export_rig,
    is_rig_document,
    load_model_any,
    parse_pinhole,
    parse_rotation,
    rig_from_dict,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True,
                   help="camera model: phasecal model.json, mrcal .cameramodel or OpenCV YAML; "
                        "or a rig model (phasecal.rig/1)")
    p.add_argument("--format", required=True, dest="fmt",
                   choices=["opencv-yaml", "ros", "mrcal", "remap", "opencv-fit", *RIG_FORMATS])
    p.add_argument("--camera", help="rig: the camera to export (single-camera formats)")
    p.add_argument("--cameras", metavar="A,B",
                   help="rig: the camera pair of opencv-stereo / stereo-remap (X2 = R X1 + T)")
    p.add_argument("-o", "--output", required=True, help="output file")
    p.add_argument("--pinhole", metavar="FX,FY,CX,CY,W,H",
                   help="remap: the virtual pinhole camera (default: an OpenCV model's own K)")
    p.add_argument("--rotation", metavar="RX,RY,RZ|R9",
                   help="remap: virtual-from-model rotation, Rodrigues (rad) or 9 numbers")
    p.add_argument("--align-to", metavar="MODEL",
                   help="remap: put the virtual camera in this model's frame (e.g. the OpenCV "
                        "calibration whose K --pinhole is; see docs/exports.md)")
    p.add_argument("--camera-name", default="camera", help="ros: camera_name (default camera)")
    p.add_argument("--approximate", action="store_true",
                   help="mrcal: fit mrcal's splined model to a fisheye model (no exact form)")
    p.add_argument("--spline-nx", type=int, default=16,
                   help="mrcal spline fit: knots across the field of view (default 16)")
    p.add_argument("--opencv-kind", default="opencv-rational",
                   choices=["opencv5", "opencv-rational"], help="opencv-fit: model to fit")


def options_from_args(args: argparse.Namespace) -> object:
    """ExportOptions from the parsed command line (shared with undistort-points)."""
    return ExportOptions(
        pinhole=parse_pinhole(args.pinhole) if args.pinhole else None,
        rotation=parse_rotation(args.rotation) if args.rotation else None,
        align_to=load_model_any(args.align_to) if getattr(args, "align_to", None) else None,
        camera_name=getattr(args, "camera_name", "camera"),
        approximate=getattr(args, "approximate", False),
        spline_nx=getattr(args, "spline_nx", 16),
        opencv_kind=getattr(args, "opencv_kind", "opencv-rational"),
    )


def _rig_document(path: str) -> dict | None:
    """The parsed JSON of `path` if it is a rig model, else None (other loaders take it)."""
    if Path(path).suffix.lower() != ".json":
        return None
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return data if is_rig_document(data) else None


def run_rig(args: argparse.Namespace, data: dict) -> int:
    """Export from a rig model: one camera, a camera pair, or the rig's transforms."""
    rig = rig_from_dict(data, source=args.model)
    pair = None
    if args.cameras is not None:
        names = [c.strip() for c in args.cameras.split(",")]
        if len(names) != 2 or not all(names):
            raise UserError(f"--cameras: expected two camera names A,B, got {args.cameras!r}")
        pair = (names[0], names[1])
    info = export_rig(rig, args.fmt, args.output, camera=args.camera, cameras=pair,
                      opts=options_from_args(args))
    what = (f"cameras {pair[0]}, {pair[1]}" if args.fmt in ("opencv-stereo", "stereo-remap")
            else f"camera {args.camera}" if args.camera else f"{len(rig.cameras)} cameras")
    line = f"wrote {args.output}: {args.fmt} of rig {what}"
    if "seen_fraction" in info:
        line += f"; {info['seen_fraction']:.1%} of the rectified images seen ({info['method']})"
    print(line)
    return 0


def run(args: argparse.Namespace) -> int:
    if args.spline_nx < 4:
        raise UserError(f"--spline-nx: expected >= 4 (cubic spline), got {args.spline_nx}")
    rig_data = _rig_document(args.model)
    if rig_data is not None:
        return run_rig(args, rig_data)
    if args.camera or args.cameras:
        raise UserError(f"--camera/--cameras: {args.model} is a single-camera model, not a rig")
    if args.fmt in RIG_FORMATS:
        raise UserError(f"--format {args.fmt}: needs a rig model (phasecal.rig/1)")
    model = load_model_any(args.model)
    info = export_model(model, args.fmt, args.output, options_from_args(args))
    line = f"wrote {args.output}: {args.fmt} of a {model.type_name} model"
    if "lensmodel" in info:
        line += f" ({info['lensmodel'].split('_fov')[0]})"
    resid = info.get("residual")
    if resid:
        line += (f"; approximation residual RMS {resid['rms_px']:.4g} px, max "
                 f"{resid['max_px']:.4g} px")
    if "seen_fraction" in info:
        line += f"; {info['seen_fraction']:.1%} of the virtual image seen"
    print(line)
    return 0
