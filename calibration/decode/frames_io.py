"""Read captured frames (docs/formats.md): one (F, H, W) `.npy`, or a folder frame_0000.png/.tif...

The `.npy` is memory-mapped (no copy). A folder's images are decoded by a few threads: into
one (F, H, W) array when it fits in a quarter of the memory (the decoder's compiled
whole-stack pass is then used), else yielded one at a time so a pose never needs the whole
stack in memory.
"""

from __future__ import annotations

import os
import re
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
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
    _read: list[np.ndarray] = field(default_factory=list, compare=False, repr=False)

    def __len__(self) -> int:
        return self.count

    def array(self) -> np.ndarray | None:
        """The whole stack: the `.npy` memory-mapped (no copy), a folder's images read into
        one array if it fits in a quarter of the memory; else None (iterate instead)."""
        if not self.files:
            prefetch(self.path)
            return np.load(self.path, mmap_mode="r", allow_pickle=False)
        if not self._read:
            nbytes = self.count * self.shape[0] * self.shape[1] * self.dtype.itemsize
            if nbytes > _memory_bytes() // 4:
                return None
            stack = np.empty((self.count, *self.shape), dtype=self.dtype)
            for i, img in enumerate(self._images()):
                stack[i] = img
            self._read.append(stack)  # iterating later yields these, not a second read
        return self._read[0]

    def __iter__(self) -> Iterator[np.ndarray]:
        if self._read or not self.files:
            stack = (self._read[0] if self._read
                     else np.load(self.path, mmap_mode="r", allow_pickle=False))
            for i in range(self.count):
                yield np.ascontiguousarray(stack[i])
            return
        yield from self._images()

    def _images(self) -> Iterator[np.ndarray]:
        """The folder's images in order (read ahead by threads), each checked against the
        first frame's shape and dtype."""
        for f, img in zip(self.files, _read_ahead(self.files), strict=True):
            if img.shape != self.shape or img.dtype != self.dtype:
                raise DecodeError(
                    f"{f}: {img.dtype} image of shape {img.shape} differs from the first "
                    f"frame ({self.dtype}, {self.shape})"
                )
            yield img


def _memory_bytes() -> int:
    """Physical memory in bytes, or the cgroup's limit if lower (a container); 4 GiB assumed
    where neither can be read."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        total = 4 << 30
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
    except OSError:
        return total
    return min(total, int(limit)) if limit.isdigit() else total


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
