"""Read captured frames (FORMATS.md): one (F, H, W) `.npy`, or a folder frame_0000.png/.tif...

Frames are yielded one at a time (the `.npy` is memory-mapped, images are read lazily) so
that decoding a pose never holds the whole stack in memory.
"""

from __future__ import annotations

import os
import re
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.decode.accumulate import ACCEPTED_DTYPES, DecodeError
from calibration.readahead import prefetch

_NAME = re.compile(r"^frame_(\d{4,})\.(png|tif|tiff)$", re.IGNORECASE)


@dataclass(frozen=True)
class FrameSource:
    """Frames in plan order from a file or folder; iterate to read them one by one."""

    path: Path
    count: int
    shape: tuple[int, int]
    dtype: np.dtype
    files: tuple[Path, ...] = ()

    def __len__(self) -> int:
        return self.count

    def array(self) -> np.ndarray | None:
        """The whole `.npy` stack, memory-mapped (no copy); None for a folder of images."""
        if self.files:
            return None
        prefetch(self.path)
        return np.load(self.path, mmap_mode="r", allow_pickle=False)

    def __iter__(self) -> Iterator[np.ndarray]:
        if not self.files:
            stack = np.load(self.path, mmap_mode="r", allow_pickle=False)
            for i in range(self.count):
                yield np.ascontiguousarray(stack[i])
            return
        for f, img in zip(self.files, _read_ahead(self.files), strict=True):
            if img.shape != self.shape or img.dtype != self.dtype:
                raise DecodeError(
                    f"{f}: {img.dtype} image of shape {img.shape} differs from the first "
                    f"frame ({self.dtype}, {self.shape})"
                )
            yield img


def _read_ahead(files: tuple[Path, ...]) -> Iterator[np.ndarray]:
    """The images in order, decoded by a few threads a few frames ahead of the consumer
    (cv2 releases the GIL while it reads and decodes; at most `2 * threads` held)."""
    threads = max(1, min(os.cpu_count() or 1, 4))
    with ThreadPoolExecutor(threads, thread_name_prefix="frames") as pool:
        pending: deque[Future[np.ndarray]] = deque()
        try:
            for f in files:
                pending.append(pool.submit(_read_image, f))
                if len(pending) >= 2 * threads:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:  # consumer stopped early (error, cancel): drop the frames not yet started
            for fut in pending:
                fut.cancel()


def _read_image(path: Path) -> np.ndarray:
    """One single-channel 8/16-bit PNG or TIFF, unchanged."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DecodeError(f"{path}: not a readable PNG/TIFF image")
    if img.ndim != 2:
        raise DecodeError(f"{path}: expected a single-channel image, got shape {img.shape}")
    if img.dtype not in (np.uint8, np.uint16):
        raise DecodeError(f"{path}: expected 8 or 16 bit pixels, got {img.dtype}")
    return img


def _from_npy(path: Path) -> FrameSource:
    try:
        stack = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise DecodeError(f"{path}: not a readable .npy array ({exc})") from None
    if stack.ndim != 3:
        raise DecodeError(f"{path}: expected a (F, H, W) array, got shape {stack.shape}")
    if stack.dtype not in ACCEPTED_DTYPES:
        raise DecodeError(
            f"{path}: dtype {stack.dtype} not supported; expected uint8, uint16 or float32"
        )
    done = path.with_suffix(".done")  # a capture's frame store marks each stored frame
    if done.is_file():
        stored = int(np.count_nonzero(np.fromfile(done, dtype=np.uint8)))
        if stored != stack.shape[0]:
            raise DecodeError(f"{path}: incomplete capture, {stored} of {stack.shape[0]} "
                              f"frames stored ({done.name}); resume the capture first")
    return FrameSource(path, int(stack.shape[0]), tuple(stack.shape[1:]), stack.dtype)


def _from_dir(path: Path) -> FrameSource:
    numbered = {}
    for f in path.iterdir():
        m = _NAME.match(f.name)
        if m:
            n = int(m.group(1))
            if n in numbered:
                raise DecodeError(f"{path}: two files for frame {n}: {numbered[n].name}, {f.name}")
            numbered[n] = f
    if not numbered:
        raise DecodeError(f"{path}: no frame_0000.png/.tif files found")
    gaps = sorted(set(range(max(numbered) + 1)) - set(numbered))
    if gaps:
        raise DecodeError(f"{path}: frames missing from the sequence: {gaps[:10]}")
    files = tuple(numbered[i] for i in range(len(numbered)))
    first = _read_image(files[0])
    return FrameSource(path, len(files), tuple(first.shape), first.dtype, files)


def read_frames(path: str | Path) -> FrameSource:
    """Open a `.npy` stack or a folder of numbered images (raises `DecodeError` if malformed)."""
    p = Path(path)
    if p.is_dir():
        return _from_dir(p)
    if not p.exists():
        raise DecodeError(f"{p}: frames file or folder not found")
    if p.suffix.lower() != ".npy":
        raise DecodeError(f"{p}: expected a .npy stack or a folder of frame_NNNN.png/.tif")
    return _from_npy(p)
