"""Validate uploaded frames (a `.npy` stack or PNG/TIFF images) against a plan and store them.

Uploads are checked before anything is decoded: count, shape, dtype and names must
match the plan (docs/formats.md, "Captured frames"); files are written under our own names.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

from api.problems import Problem
from calibration.shared.plan import Plan

IMAGE_RE = re.compile(r"^frame_(\d{4,6})\.(png|tif|tiff)$", re.IGNORECASE)
NPY_DTYPES = (np.uint8, np.uint16, np.float32)


def store_npy(upload: BinaryIO, name: str, plan: Plan, dest: Path) -> tuple[int, int]:
    """Copy an uploaded `.npy` stack to `dest` and check it; returns (H, W)."""
    with open(dest, "wb") as fh:
        shutil.copyfileobj(upload, fh, length=1 << 20)
    try:
        arr = np.load(dest, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise Problem(422, "invalid-frames", f"{name}: not a readable .npy array ({exc})") from None
    if not isinstance(arr, np.ndarray) or arr.ndim != 3:
        shape = getattr(arr, "shape", None)
        raise Problem(422, "invalid-frames",
                      f"{name}: expected a (F, H, W) array, got shape {shape}")
    if arr.dtype not in NPY_DTYPES:
        raise Problem(422, "invalid-frames",
                      f"{name}: dtype {arr.dtype} not supported; use uint8, uint16 or float32")
    _check_count(arr.shape[0], plan, name)
    if arr.shape[1] < 2 or arr.shape[2] < 2:
        raise Problem(422, "invalid-frames", f"{name}: frames of {arr.shape[1:]} px are too small")
    return int(arr.shape[1]), int(arr.shape[2])


def store_images(files: list[tuple[str, bytes]], plan: Plan, folder: Path) -> tuple[int, int]:
    """Check uploaded `frame_NNNN.png|tif` images and write them to `folder`; returns (H, W)."""
    by_index: dict[int, tuple[str, bytes]] = {}
    for name, data in files:
        m = IMAGE_RE.match(name or "")
        if not m:
            raise Problem(422, "invalid-frames",
                          f"{name!r}: image names must be frame_0000.png (or .tif) in plan order")
        idx = int(m.group(1))
        if idx in by_index:
            raise Problem(422, "invalid-frames", f"{name!r}: frame {idx} was uploaded twice")
        by_index[idx] = (name, data)
    _check_count(len(by_index), plan, "images")
    missing = [i for i in range(len(plan.frames)) if i not in by_index]
    if missing:
        raise Problem(422, "invalid-frames", f"images: frame {missing[0]} is missing")
    shape: tuple[int, int] | None = None
    dtype, first = None, ""
    folder.mkdir(parents=True, exist_ok=True)
    for idx in sorted(by_index):
        name, data = by_index[idx]
        if not data:
            raise Problem(422, "invalid-frames", f"{name}: empty file")
        try:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error:
            img = None
        if img is None:
            raise Problem(422, "invalid-frames", f"{name}: not a readable PNG/TIFF image")
        if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
            raise Problem(422, "invalid-frames",
                          f"{name}: expected a single-channel 8- or 16-bit image, got "
                          f"{img.dtype} with shape {img.shape}")
        if shape is None:
            shape, dtype, first = (int(img.shape[0]), int(img.shape[1])), img.dtype, name
        elif img.shape != shape:
            raise Problem(422, "invalid-frames",
                          f"{name}: shape {img.shape} differs from {first} {shape}")
        elif img.dtype != dtype:
            raise Problem(422, "invalid-frames",
                          f"{name}: {img.dtype} differs from {first} ({dtype}); one pose has "
                          "one bit depth")
        ext = ".png" if name.lower().endswith(".png") else ".tif"
        (folder / f"frame_{idx:04d}{ext}").write_bytes(data)
    assert shape is not None
    return shape


def _check_count(count: int, plan: Plan, name: str) -> None:
    if count != len(plan.frames):
        raise Problem(422, "frames-plan-mismatch",
                      f"{name}: {count} frames but the session's plan has {len(plan.frames)}")
