"""Capture a pose on a rig into a frames folder (resumable), then decode on the executor.

Frames go to `frame_NNNN.png` files (FORMATS.md folder layout), each written
atomically as it is accepted, so a capture cut off by a restart resumes at the first
missing frame and the folder can also be decoded by `phasecal decode`.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibration.plan import Plan
from calibration.progress import TaskContext

FRAME_RE = re.compile(r"^frame_(\d{4,6})\.(png|tif|tiff)$")


class PngFrameSink:
    """A `FrameSink` writing each accepted frame to `frame_NNNN.png` atomically."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)

    def add(self, index: int, image: np.ndarray) -> None:
        """Store frame `index` (uint8/uint16, 2-D)."""
        img = np.asarray(image)
        if img.dtype not in (np.uint8, np.uint16):
            raise ValueError(f"frame {index}: expected uint8/uint16 image, got {img.dtype}")
        ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise OSError(f"frame {index}: PNG encoding failed")
        path = self.folder / f"frame_{index:04d}.png"
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as fh:
            fh.write(buf.tobytes())
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)


def stored_indices(folder: Path) -> set[int]:
    """Plan indices already captured in `folder`."""
    if not folder.is_dir():
        return set()
    return {int(m.group(1)) for p in folder.iterdir() if (m := FRAME_RE.match(p.name))}


class _SkipSink:
    """Forwards frames not yet stored; counts progress over the whole plan."""

    def __init__(self, sink: PngFrameSink, have: set[int], ctx: TaskContext, total: int) -> None:
        self.sink, self.have, self.ctx, self.total = sink, set(have), ctx, total

    def add(self, index: int, image: np.ndarray) -> None:
        if index not in self.have:
            self.sink.add(index, image)
            self.have.add(index)
        self.ctx.progress(len(self.have), self.total, "capture")


def capture_frames(ctx: TaskContext, rig: Any, plan: Plan, folder: Path) -> dict[str, Any]:
    """Run the controller for the plan frames missing in `folder`; raise on failure/cancel."""
    from acquisition.controller import capture_pose

    have = stored_indices(folder)
    total = len(plan.frames)
    ctx.progress(len(have), total, "capture")
    missing = [i for i in range(total) if i not in have]
    if not missing:
        return {"captured": 0, "resumed_from": len(have)}
    sink = _SkipSink(PngFrameSink(folder), have, ctx, total)
    result = capture_pose(rig, plan, sink, indices=missing, progress=None,
                          cancelled=ctx.cancelled)
    ctx.check_cancelled()
    status = getattr(result, "status", "complete")
    if status not in ("complete", "flagged"):
        reason = getattr(result, "reason", "") or status
        raise RuntimeError(f"capture {status}: {reason}")
    left = [i for i in range(total) if i not in stored_indices(folder)]
    if left:
        raise RuntimeError(f"capture ended with {len(left)} plan frames missing (first {left[0]})")
    out: dict[str, Any] = {"captured": len(missing), "resumed_from": len(have)}
    if status == "flagged":
        out["flagged"] = getattr(result, "reason", "")
    return out
