"""`phasecal undistort-points`: model pixels -> pixels of a virtual pinhole camera."""

from __future__ import annotations

import argparse

import numpy as np

from api.commands.export import options_from_args
from api.commands.unproject import load_array
from calibration import load_model_any, undistort_pixels


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True,
                   help="camera model: phasecal model.json, mrcal .cameramodel or OpenCV YAML")
    p.add_argument("--pixels", required=True, help="float64 (N, 2) .npy of model pixels")
    p.add_argument("-o", "--output", required=True, help="output (N, 2) .npy, NaN if not seen")
    p.add_argument("--pinhole", metavar="FX,FY,CX,CY[,W,H]",
                   help="virtual pinhole (default: an OpenCV model's own K)")
    p.add_argument("--rotation", metavar="RX,RY,RZ|R9",
                   help="virtual-from-model rotation, Rodrigues (rad) or 9 numbers")
    p.add_argument("--align-to", metavar="MODEL",
                   help="put the virtual camera in this model's frame (see docs/exports.md)")


def run(args: argparse.Namespace) -> int:
    if args.pinhole and args.pinhole.count(",") == 3:
        args.pinhole += ",1,1"  # the size does not matter for points
    model = load_model_any(args.model)
    pix = load_array(args.pixels, 2, "--pixels")
    out = undistort_pixels(model, pix, options_from_args(args))
    np.save(args.output, out)
    ok = int(np.all(np.isfinite(out), axis=1).sum())
    print(f"wrote {args.output}: {len(out)} points ({ok} in front of the virtual camera)")
    return 0
