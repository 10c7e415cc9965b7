"""`phasecal export`: a model to OpenCV YAML, ROS camera_info, mrcal, remap maps or opencv-fit."""

from __future__ import annotations

import argparse

from api.cli import UserError
from calibration import (
    ExportOptions,
    export_model,
    load_model_any,
    parse_pinhole,
    parse_rotation,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True,
                   help="camera model: phasecal model.json, mrcal .cameramodel or OpenCV YAML")
    p.add_argument("--format", required=True, dest="fmt",
                   choices=["opencv-yaml", "ros", "mrcal", "remap", "opencv-fit"])
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


def run(args: argparse.Namespace) -> int:
    if args.spline_nx < 4:
        raise UserError(f"--spline-nx: expected >= 4 (cubic spline), got {args.spline_nx}")
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
