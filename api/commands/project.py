"""`phasecal project`: camera-frame 3D points (N, 3) mm -> pixels (N, 2) through a model."""

from __future__ import annotations

import argparse

import numpy as np

from api.commands.unproject import load_array, load_camera


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True,
                   help="camera model (phasecal.model/1 JSON) or rig model (phasecal.rig/1)")
    p.add_argument("--camera", help="rig: project into this camera; the points are then in "
                                    "the rig's reference camera frame")
    p.add_argument("--points", required=True,
                   help="float64 (N, 3) .npy, mm, camera frame (a rig: reference frame)")
    p.add_argument("-o", "--output", required=True, help="output pixels.npy (N, 2), NaN if unseen")


def run(args: argparse.Namespace) -> int:
    model = load_camera(args.model, args.camera)
    pts = load_array(args.points, 3, "--points")
    pix = np.asarray(model.project(pts), dtype=np.float64)
    np.save(args.output, pix)
    seen = int(np.all(np.isfinite(pix), axis=1).sum())
    print(f"wrote {args.output}: {pix.shape[0]} pixels ({seen} seen)")
    return 0
