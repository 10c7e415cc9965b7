"""Raw frame store of one pose: `frames.npy` (F, H, W), memory-mapped, plus `frames.done`.

`frames.npy` is the docs/formats.md `.npy` stack (np.load and `phasecal decode` read it; its
header is padded to 4 KiB so every frame starts on a disk block); `frames.done` holds one
byte per plan frame, set to 1 after that frame's pixels were written in. No encoding and no
fsync on the capture loop: a store written for a live decode (`stage=True`) copies each frame
into a resident shared-memory slot (`frame_staging`) and writes it to disk from there with
O_DIRECT, and the decode reads the slot; otherwise a frame is a `pwrite` into the page cache.
Either way the data survive a killed process at once, and a background flusher makes them
durable on disk at a bounded interval and when the store is closed (pixels first, then the
markers, so a durable marker implies durable pixels). A reader in another process (the
decode worker) maps the same files and follows the markers.
"""

from __future__ import annotations

import errno
import os
import struct
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from calibration.decode.accumulate import ACCEPTED_DTYPES, DecodeError
from calibration.shared.atomic import allocate, fsync_path
from calibration.shared.frame_staging import (
    POOL,
    StagedFrames,
    StagingBuffer,
    write_sidecar,
)
from calibration.shared.npz_store import npy_header

FRAMES_NAME = "frames.npy"
DONE_NAME = "frames.done"
_BLOCK = 4096  # frames.npy's data offset: O_DIRECT writes need block-aligned offsets
_DIRECT_ALIGN = 512  # ... and lengths and memory aligned to the disk's logical block


def padded_npy_header(shape: tuple[int, ...], dtype: np.dtype) -> bytes:
    """The .npy (1.0) header of a C-order array padded with spaces to `_BLOCK` bytes (a valid
    header: NumPy reads its length from the header)."""
    head = npy_header(shape, np.dtype(dtype))
    body = head[10:-1].ljust(_BLOCK - 11) + b"\n"
    return head[:8] + struct.pack("<H", len(body)) + body


class FrameStore:
    """Writer and reader of one pose's raw frames (a `FrameSink` when writing)."""

    def __init__(self, folder: str | Path, count: int | None = None, *,
                 flush_interval_s: float = 2.0, stage: bool = False) -> None:
        self.folder = Path(folder)
        self.count = count  # plan frames; None: read from an existing store
        self.flush_interval_s = flush_interval_s
        self.stage = stage  # writer: stage frames for a live decode (module docstring)
        self._staging: StagingBuffer | None = None  # writer: the leased buffer
        self._slots: np.ndarray | None = None  # ... its (F, H, W) slots
        self._direct_fd: int | None = None  # frames.npy opened with O_DIRECT
        self._staged: StagedFrames | None = None  # reader: the writer's buffer, once found
        self._frames: np.memmap | None = None  # read-only map: frames are written by `_write`
        self._writable = False
        self._fd: int | None = None  # frames.npy opened for writing
        self._done: np.memmap | None = None
        self._dirty = False
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._flusher: threading.Thread | None = None
        self.last_index: int | None = None  # the frame stored last (live preview)

    # -- paths and state ---------------------------------------------------------------
    @property
    def frames_path(self) -> Path:
        return self.folder / FRAMES_NAME

    @property
    def done_path(self) -> Path:
        return self.folder / DONE_NAME

    def exists(self) -> bool:
        """True once the first frame created the files."""
        return self.frames_path.is_file() and self.done_path.is_file()

    def _open(self, writable: bool) -> bool:
        """Map existing files; False when there are none yet."""
        if self._frames is not None and (self._writable or not writable):
            return True
        if not self.exists():
            return False
        mode = "r+" if writable else "r"
        frames = np.load(self.frames_path, mmap_mode="r", allow_pickle=False)
        if self.count is None and frames.ndim == 3:
            self.count = int(frames.shape[0])
        if frames.ndim != 3 or frames.shape[0] != self.count:
            raise DecodeError(f"{self.frames_path}: shape {frames.shape} does not hold "
                              f"{self.count} plan frames")
        self._done = np.memmap(self.done_path, dtype=np.uint8, mode=mode, shape=(self.count,))
        self._frames, self._writable = frames, writable
        return True

    def stored(self) -> np.ndarray:
        """Indices of the frames stored so far (ascending)."""
        if not self._open(writable=False):
            return np.empty(0, dtype=np.int64)
        return np.flatnonzero(np.array(self._done))  # a snapshot: the writer may be adding

    def frame(self, index: int) -> np.ndarray:
        """A read-only view of stored frame `index` (no copy)."""
        if not self._open(writable=False):
            raise DecodeError(f"{self.frames_path}: no frames stored")
        slots, staging = self._slots, self._staging
        view = (slots[index] if slots is not None and staging is not None
                and staging.holds(index) else self._frames[index])
        view = view.view()
        view.flags.writeable = False
        return view

    def array(self) -> np.ndarray:
        """The whole (F, H, W) store, memory-mapped read-only (rows of unstored frames are
        zeros); `StreamingDecoder.add_frames` folds in the stored ones in one pass."""
        if not self._open(writable=False):
            raise DecodeError(f"{self.frames_path}: no frames stored")
        return self._frames

    def sources(self, indices: list[int]) -> list[tuple[list[int], np.ndarray]]:
        """The stored frames `indices` grouped by where a reader takes them: (plan indices,
        an (F, H, W) stack indexed by plan index); the staged ones from the writer's shared
        memory when it still serves this pose (`verify` after reading them)."""
        if self._staged is not None and not self._staged.current():  # given to another pose
            self.reader_done()  # (this pose's frames are all in frames.npy)
        if self._staged is None and self.count is not None:
            self._staged = StagedFrames.attach(self.folder, self.count)
        staged = self._staged.staged(indices) if self._staged is not None else []
        held = set(staged)
        rest = [i for i in indices if i not in held]
        out = [(staged, self._staged.frames)] if staged else []
        if rest:
            out.append((rest, self.array()))
        return out

    def verify(self) -> None:
        """Raise if frames read through `sources` since may not be this pose's (the shared
        memory they came from was given to another capture meanwhile)."""
        if self._staged is not None:
            self._staged.check()

    def reader_done(self) -> None:
        """A reader of `sources` is done: the writer's shared memory may serve another pose."""
        if self._staged is not None:
            self._staged.done()
            self._staged.close()
            self._staged = None

    # -- writing -----------------------------------------------------------------------
    def _create(self, image: np.ndarray) -> None:
        """Create both files for frames like `image` (temp names, then renames)."""
        if self.count is None:
            raise DecodeError(f"{self.folder}: the number of plan frames is needed to create "
                              "a frame store")
        self.folder.mkdir(parents=True, exist_ok=True)
        shape = (self.count, *image.shape)
        done_tmp = self.done_path.with_name(DONE_NAME + ".tmp")
        tmp = self.frames_path.with_name(FRAMES_NAME + ".tmp")
        try:
            # both files get their blocks now (the markers are written through a map, where
            # a full disk would be a SIGBUS): a disk too small for the pose fails here, at
            # its first frame, with ENOSPC, and a capture that started never runs out
            with open(done_tmp, "wb") as fh:
                fh.write(bytes(self.count))
            header = padded_npy_header(shape, image.dtype)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                os.write(fd, header)
                allocate(fd, len(header) + self.count * image.nbytes)
            finally:
                os.close(fd)
        except OSError:
            done_tmp.unlink(missing_ok=True)
            tmp.unlink(missing_ok=True)
            raise
        self._start_staging(image)  # (named before a reader can see the store)
        os.replace(done_tmp, self.done_path)
        os.replace(tmp, self.frames_path)

    def add(self, index: int, image: np.ndarray) -> None:
        """Store plan frame `index`: copy into the mapped file, then mark it stored."""
        img = np.asarray(image)
        if img.ndim != 2 or img.dtype not in ACCEPTED_DTYPES:
            raise DecodeError(f"frame {index}: expected a 2-D uint8/uint16/float32 image, "
                              f"got {img.dtype} {img.shape}")
        with self._lock:
            if not self._open(writable=True):
                self._create(img)
                self._open(writable=True)
            elif self.stage and self._staging is None:
                self._start_staging(img)  # (a store resumed: its earlier frames stay on disk)
            if self._frames.shape[1:] != img.shape or self._frames.dtype != img.dtype:
                raise DecodeError(f"frame {index}: {img.dtype} {img.shape} differs from the "
                                  f"stored frames ({self._frames.dtype} "
                                  f"{self._frames.shape[1:]})")
            self._write(index, img)
            self._done[index] = 1
            self._dirty = True
            self.last_index = int(index)
            if self._flusher is None and self.flush_interval_s > 0:
                self._flusher = threading.Thread(target=self._flush_loop, daemon=True,
                                                 name="frame-store-flush")
                self._flusher.start()

    def _start_staging(self, image: np.ndarray) -> None:
        """Lease a shared-memory buffer for this store's frames (`stage`), name it to readers
        and open frames.npy for O_DIRECT writes where the layout allows; nothing where no
        buffer is to be had (the page cache then)."""
        if not self.stage or self.count is None:
            return
        self.stage = False  # (once per store)
        buf = POOL.lease(self.count, image.nbytes)
        if buf is None:
            return
        self._staging, self._slots = buf, buf.frames(image.shape, image.dtype)
        write_sidecar(self.folder, buf, image.shape, image.dtype)
        offset = len(padded_npy_header((self.count, *image.shape), image.dtype))
        if image.nbytes % _DIRECT_ALIGN == 0 and self._data_offset(offset) % _BLOCK == 0:
            try:
                self._direct_fd = os.open(self._writable_path(), os.O_WRONLY | os.O_DIRECT)
            except (OSError, AttributeError):  # (a filesystem without O_DIRECT: tmpfs)
                self._direct_fd = None

    def _data_offset(self, new: int) -> int:
        """Where frames.npy's pixels start: its map's offset, `new` for a store being made."""
        return self._frames.offset if self._frames is not None else new

    def _writable_path(self) -> Path:
        """frames.npy, or its temporary name while `_create` makes it."""
        if self.frames_path.is_file():
            return self.frames_path
        return self.frames_path.with_name(FRAMES_NAME + ".tmp")

    def _write(self, index: int, img: np.ndarray) -> None:
        """Write frame `index`'s pixels into frames.npy: staged, from its shared-memory slot
        with O_DIRECT (module docstring); else with `pwrite` into the page cache (as a store
        through the map would, but there a write fault on a new page first reads ahead and
        zeroes a whole (large) folio that the copy then overwrites: 11 against 8 CPU ms per
        5 MB frame on a 2-vCPU VM)."""
        assert self._frames is not None
        at = self._frames.offset + int(index) * img.nbytes
        if self._staging is not None and self._slots is not None:
            slot = self._staging.put(int(index), img, self._slots)
            if self._direct_fd is not None:
                try:
                    self._pwrite(self._direct_fd, slot, at)
                    return
                except OSError as exc:  # alignment the disk does not take: buffered from now
                    if exc.errno != errno.EINVAL:
                        raise
                    os.close(self._direct_fd)
                    self._direct_fd = None
        if self._fd is None:
            self._fd = os.open(self.frames_path, os.O_WRONLY)
        self._pwrite(self._fd, memoryview(np.ascontiguousarray(img)).cast("B"), at)

    @staticmethod
    def _pwrite(fd: int, data: memoryview, at: int) -> None:
        while data:  # (a regular file takes it all at once; a short write continues)
            n = os.pwrite(fd, data, at)
            data, at = data[n:], at + n

    def flush(self) -> None:
        """Make the stored frames durable: pixels first, then the markers.

        `fsync` on the files (it covers their pages written through the maps) rather than
        `msync`: Python's mmap flush holds the GIL for the whole write-back (160 ms for
        300 MB here), which would stall the capture thread; `os.fsync` releases it."""
        with self._lock:
            if self._frames is None or not self._dirty:
                return
            self._dirty = False
        for path in (self.frames_path, self.done_path):
            fsync_path(path)

    def _flush_loop(self) -> None:
        while not self._stop.wait(self.flush_interval_s):
            try:
                self.flush()
            except OSError:  # (an I/O error) marked dirty again: `close` flushes and raises it
                with self._lock:
                    self._dirty = True
                return

    def close(self) -> None:
        """Stop the flusher and flush what is left (end of the pose's capture)."""
        self._stop.set()
        if self._flusher is not None:
            self._flusher.join()
            self._flusher = None
        self.flush()
        with self._lock:
            for fd in (self._fd, self._direct_fd):
                if fd is not None:
                    os.close(fd)
            self._fd = self._direct_fd = None
            if self._staging is not None:  # its reader, if any, removes the sidecar
                POOL.give_back(self._staging)
                self._staging = self._slots = None

    def wait_open(self, cancelled: Any, poll_s: float = 0.005) -> None:
        """Block until the writer created the files (polling `cancelled()`)."""
        while not self._open(writable=False):
            if cancelled():
                return
            time.sleep(poll_s)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the stored frames."""
        if not self._open(writable=False):
            raise DecodeError(f"{self.frames_path}: no frames stored")
        return tuple(self._frames.shape[1:])  # type: ignore[return-value]
