"""`phasecal unproject`: pixels (N, 2) -> rays (origins, directions) through a model."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from api.cli import UserError
from calibration import load_model


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True, help="camera model (phasecal.model/1 JSON)")
    p.add_argument("--pixels", required=True, help="float64 (N, 2) .npy of (u, v)")
    p.add_argument("-o", "--output", required=True, help="output rays.npz")


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
    model = load_model(args.model)
    pix = load_array(args.pixels, 2, "--pixels")
    origins, directions = model.unproject(pix)
    out = args.output if args.output.endswith(".npz") else args.output + ".npz"
    np.savez(out, origins=np.asarray(origins, np.float64),
             directions=np.asarray(directions, np.float64))
    ok = int(np.all(np.isfinite(directions), axis=1).sum())
    print(f"wrote {out}: {pix.shape[0]} rays ({ok} defined)")
    return 0
