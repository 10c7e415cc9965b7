"""`phasecal unproject`: pixels (N, 2) -> rays (origins, directions) through a model."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from api.cli import UserError
from calibration import CameraModel, RigCamera, is_rig_document, load_model, rig_from_dict


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True,
                   help="camera model (phasecal.model/1 JSON) or rig model (phasecal.rig/1)")
    p.add_argument("--camera", help="rig: the camera whose pixels these are; rays come out in "
                                    "the rig's reference camera frame")
    p.add_argument("--pixels", required=True, help="float64 (N, 2) .npy of (u, v)")
    p.add_argument("-o", "--output", required=True, help="output rays.npz")


def load_camera(path: str, camera: str | None) -> CameraModel | RigCamera:
    """A model file's model, or a rig file's camera `camera` (which then works in the rig's
    reference frame); a one-line error when --camera is missing for a rig or given for a
    model."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        data = None  # load_model names the problem
    if is_rig_document(data):
        rig = rig_from_dict(data, source=path)
        if camera is None:
            raise UserError(f"--camera: {path} is a rig; name one of {sorted(rig.cameras)}")
        return rig.camera(camera)
    if camera is not None:
        raise UserError(f"--camera: {path} is a single-camera model, not a rig")
    return load_model(path)


def load_array(path: str, ncols: int, flag: str) -> np.ndarray:
    """Read an (N, ncols) numeric .npy file, or raise a one-line error naming the flag."""
    if not Path(path).is_file():
        raise UserError(f"{flag}: file not found: {path}")
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise UserError(f"{flag}: {path} is not a readable .npy file ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != ncols or not np.issubdtype(arr.dtype, np.number):
        raise UserError(f"{flag}: {path}: expected a numeric (N, {ncols}) array, "
                        f"got {arr.dtype} {arr.shape}")
    return arr.astype(np.float64)


def run(args: argparse.Namespace) -> int:
    model = load_camera(args.model, args.camera)
    pix = load_array(args.pixels, 2, "--pixels")
    origins, directions = model.unproject(pix)
    out = args.output if args.output.endswith(".npz") else args.output + ".npz"
    np.savez(out, origins=np.asarray(origins, np.float64),
             directions=np.asarray(directions, np.float64))
    ok = int(np.all(np.isfinite(directions), axis=1).sum())
    print(f"wrote {out}: {pix.shape[0]} rays ({ok} defined)")
    return 0
