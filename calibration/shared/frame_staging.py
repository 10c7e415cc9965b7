"""Resident shared memory for the frames of a pose while it is captured.

Storing a frame through the page cache costs the capture side a copy into pages the
system allocates for it, pose after pose: 1.3-7.5 CPU s per GB of frames on a 2-vCPU VM
(fresh guest pages fault on the host), ~0.2 on bare metal, and the decode worker then
reads the frames back through those pages. With staging, the capture side copies each frame
into a slot of a shared-memory buffer that is reused pose after pose (its pages stay
resident), writes it to `frames.npy` from there with O_DIRECT (the disk takes it by DMA,
~0.03 CPU s per GB), and the live decode in another process reads the slot.

A buffer (`StagingBuffer`) is a file in /dev/shm: a 4 KiB header (a token that changes
before a new pose writes any slot, whether the reader is done, one "staged" byte per frame)
and one slot per plan frame, `frames.npy`'s layout. The capture side leases one per camera
from its process's `StagingPool`; the pose's frame store names it to readers in a sidecar
file (`frames.staging`). A reader (`StagedFrames`) uses a slot only while the token is the
one the sidecar named, and says so (`check`) after each read: a buffer reused under a
reader that fell behind fails that decode with the reason rather than feeding it another
pose's pixels. The sidecar stays until the reader is done (a reader that starts late, after
the capture, still finds the buffer). Where /dev/shm is missing or full, no buffer is leased
and the store writes through the page cache as before. A reading process keeps its mapping
of each buffer from pose to pose (`ReaderMappings`).
"""

from __future__ import annotations

import atexit
import json
import mmap
import os
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from calibration.decode.accumulate import DecodeError
from calibration.shared.atomic import write_json_atomic

HEADER_BYTES = 4096
_TOKEN = slice(0, 16)
_READER_DONE = 16
_STAGED = 64  # the per-frame "staged" bytes start here
MAX_FRAMES = HEADER_BYTES - _STAGED
SHM_DIR = Path("/dev/shm")
_PREFIX = "phasecal-frames-"
# At most this much shared memory is held for staging by one process (4 cameras of 5 MP
# take 1 GB; free buffers of other sizes are removed to make room); a capture beyond it
# writes through the page cache.
POOL_LIMIT_BYTES = 4 << 30
# A released buffer whose reader never said it was done is reused after this long.
REUSE_AFTER_S = 60.0
# A reader's mappings are dropped after this long without a pose, and kept for at most
# this many buffers (a rig's cameras, and the buffers that replace them).
READER_KEEP_S, READER_KEEP = 120.0, 8
SIDECAR = "frames.staging"


class StagingBuffer:
    """One shared-memory buffer of `count` frames of `nbytes` bytes (the writer's side)."""

    def __init__(self, path: Path, count: int, nbytes: int) -> None:
        self.path, self.count, self.nbytes = path, count, nbytes
        size = HEADER_BYTES + count * nbytes
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.posix_fallocate(fd, 0, size)  # tmpfs pages now: a full /dev/shm fails here
            self._mm = mmap.mmap(fd, size)
        except BaseException:
            os.close(fd)
            path.unlink(missing_ok=True)
            raise
        os.close(fd)
        self.header = np.frombuffer(self._mm, np.uint8, HEADER_BYTES)
        self.token = ""
        self.released_at: float | None = time.monotonic()  # None while leased

    def begin(self) -> str:
        """Start a new pose in this buffer: a new token first (a reader of the previous pose
        sees it change before any slot does), then no frame staged, no reader done."""
        token = uuid.uuid4()
        self.header[_TOKEN] = np.frombuffer(token.bytes, np.uint8)
        self.header[_READER_DONE] = 0
        self.header[_STAGED:_STAGED + self.count] = 0
        self.token, self.released_at = token.hex, None
        return self.token

    def frames(self, shape: tuple[int, int], dtype: np.dtype) -> np.ndarray:
        """The slots as a writable (count, H, W) array."""
        return np.ndarray((self.count, *shape), dtype=dtype, buffer=self._mm,
                          offset=HEADER_BYTES)

    def put(self, index: int, image: np.ndarray, frames: np.ndarray) -> memoryview:
        """Copy frame `index` into its slot of `frames` (this buffer's `frames`), mark it
        staged; the slot's bytes (page-aligned where `nbytes` is a multiple of 4 KiB, else
        512-byte aligned when `nbytes` is a multiple of 512: what O_DIRECT needs)."""
        np.copyto(frames[index], image)
        self.header[_STAGED + index] = 1
        start = HEADER_BYTES + index * self.nbytes
        return memoryview(self._mm)[start:start + self.nbytes]

    def holds(self, index: int) -> bool:
        """Whether frame `index` of the current pose is in its slot."""
        return bool(self.header[_STAGED + index])

    def reader_done(self) -> bool:
        """Whether the current pose's reader said it needs the buffer no more."""
        return bool(self.header[_READER_DONE])

    def reusable(self, now: float) -> bool:
        """Not leased, and its reader is done (or never said so in `REUSE_AFTER_S`)."""
        if self.released_at is None:
            return False
        return self.reader_done() or now - self.released_at >= REUSE_AFTER_S

    def close(self) -> None:
        """Unmap and remove the file (a reader that still maps it keeps its pages)."""
        self.header = np.empty(0, np.uint8)
        try:
            self._mm.close()
        except BufferError:  # views still alive: unmapped when they go
            pass
        self.path.unlink(missing_ok=True)


class StagingPool:
    """The staging buffers of this process: leased per camera and pose, kept for the next."""

    def __init__(self, folder: Path = SHM_DIR, limit_bytes: int = POOL_LIMIT_BYTES) -> None:
        self.folder, self.limit_bytes = folder, limit_bytes
        self._buffers: list[StagingBuffer] = []
        self._lock = threading.Lock()
        self._serial = 0
        self._swept = False
        atexit.register(self.close)  # (the buffers are files: removed when the process ends)

    def lease(self, count: int, nbytes: int) -> StagingBuffer | None:
        """A buffer of `count` frames of `nbytes` bytes for one pose (`begin` called), or None
        where staging cannot help (no /dev/shm, not enough room, the pool at its limit, a plan
        of more than `MAX_FRAMES` frames)."""
        if count > MAX_FRAMES or not self.folder.is_dir():
            return None
        with self._lock:
            if not self._swept:
                self._sweep_dead()
            now = time.monotonic()
            for buf in self._buffers:
                if buf.count == count and buf.nbytes == nbytes and buf.reusable(now):
                    buf.begin()
                    return buf
            if self._held() + HEADER_BYTES + count * nbytes > self.limit_bytes:
                for buf in [b for b in self._buffers if b.reusable(now)]:  # other sizes
                    buf.close()
                    self._buffers.remove(buf)
                if self._held() + HEADER_BYTES + count * nbytes > self.limit_bytes:
                    return None
            self._serial += 1
            path = self.folder / f"{_PREFIX}{os.getpid()}-{self._serial}"
            try:
                buf = StagingBuffer(path, count, nbytes)
            except OSError:  # no room in /dev/shm: the page cache it is
                return None
            self._buffers.append(buf)
            buf.begin()
            return buf

    def _held(self) -> int:
        return sum(HEADER_BYTES + b.count * b.nbytes for b in self._buffers)

    def give_back(self, buf: StagingBuffer) -> None:
        """The pose's writer is done with `buf` (its reader may still be reading)."""
        with self._lock:
            buf.released_at = time.monotonic()

    def close(self) -> None:
        """Remove every buffer (the process ends)."""
        with self._lock:
            for buf in self._buffers:
                buf.close()
            self._buffers.clear()

    def _sweep_dead(self) -> None:
        """Remove buffers left in the folder by processes that no longer run."""
        self._swept = True
        for path in self.folder.glob(f"{_PREFIX}*"):
            pid = path.name[len(_PREFIX):].split("-")[0]
            if pid.isdigit() and not _running(int(pid)):
                path.unlink(missing_ok=True)


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


POOL = StagingPool()


class ReaderMappings:
    """A reading process's mappings of staging buffers, kept from pose to pose.

    A buffer mapped afresh for each pose is read through new page-table entries: ~4000
    page faults per 250 MB (5 MP, 50 frames; the kernel maps 16 pages per fault) in the
    decode worker, every pose and camera. A kept mapping already has them. A mapping whose
    file was removed or replaced is closed at the next `get` (its memory is the file's:
    held while mapped), all of them after `READER_KEEP_S` without a `get`."""

    def __init__(self, keep: int = READER_KEEP, keep_s: float = READER_KEEP_S) -> None:
        self.keep, self.keep_s = keep, keep_s
        self._maps: dict[str, tuple[tuple[int, int, int], mmap.mmap]] = {}
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None

    def get(self, path: str) -> mmap.mmap:
        """A writable mapping of the whole buffer file `path` (OSError if it is gone)."""
        with self._lock:
            self._drop_stale()
            kept = self._maps.pop(path, None)
            fd = os.open(path, os.O_RDWR)
            try:
                st = os.fstat(fd)
                key = (st.st_dev, st.st_ino, st.st_size)
                if kept is not None and kept[0] == key:
                    mm = kept[1]
                else:
                    mm = mmap.mmap(fd, 0)
            finally:
                os.close(fd)
            self._maps[path] = (key, mm)  # (last used last)
            for old in list(self._maps)[:-self.keep]:
                _close(self._maps.pop(old)[1])
            if self._timer is not None:
                self._timer.cancel()
            self._timer = threading.Timer(self.keep_s, self.release)
            self._timer.daemon = True
            self._timer.start()
            return mm

    def _drop_stale(self) -> None:
        """Close the mappings of buffers removed or replaced since."""
        for path, (key, mm) in list(self._maps.items()):
            try:
                st = os.stat(path)
                current = (st.st_dev, st.st_ino, st.st_size) == key
            except OSError:
                current = False
            if not current:
                del self._maps[path]
                _close(mm)

    def release(self) -> None:
        """Close every kept mapping."""
        with self._lock:
            for _, mm in self._maps.values():
                _close(mm)
            self._maps.clear()

    def __len__(self) -> int:
        with self._lock:
            return len(self._maps)


def _close(mm: mmap.mmap) -> None:
    """Unmap `mm`, or leave it to the views still reading it (unmapped with the last)."""
    try:
        mm.close()
    except BufferError:
        pass


READER_MAPS = ReaderMappings()


def write_sidecar(folder: Path, buf: StagingBuffer, shape: tuple[int, int],
                  dtype: np.dtype) -> None:
    """Name `buf` (and its token) to readers of the frame store in `folder`."""
    write_json_atomic(folder / SIDECAR, {"path": str(buf.path), "token": buf.token,
                                         "count": buf.count, "shape": list(shape),
                                         "dtype": np.dtype(dtype).str})


class StagedFrames:
    """A reader's view of the staging buffer a frame store's sidecar names (`attach`)."""

    def __init__(self, info: dict[str, Any], sidecar: Path) -> None:
        self.sidecar = sidecar
        self.token = bytes.fromhex(info["token"])
        mm = READER_MAPS.get(info["path"])  # (kept for the next pose)
        self.header = np.frombuffer(mm, np.uint8, HEADER_BYTES)
        self.count = int(info["count"])
        self.frames = np.ndarray((self.count, *info["shape"]), dtype=np.dtype(info["dtype"]),
                                 buffer=mm, offset=HEADER_BYTES)
        self.frames.flags.writeable = False

    @classmethod
    def attach(cls, folder: Path, count: int) -> StagedFrames | None:
        """The buffer the sidecar in `folder` names, if it still serves that pose."""
        try:
            info = json.loads((folder / SIDECAR).read_text())
            staged = cls(info, folder / SIDECAR)
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if staged.count != count or not staged.current():
            staged.close()
            return None
        return staged

    def current(self) -> bool:
        """Whether the buffer still holds the pose the sidecar named."""
        return bytes(self.header[_TOKEN]) == self.token

    def staged(self, indices: list[int]) -> list[int]:
        """Those of `indices` whose pixels are in the buffer."""
        flags = self.header[_STAGED:_STAGED + self.count]
        return [i for i in indices if flags[i]]

    def check(self) -> None:
        """Raise if the buffer was given to another pose (what was read may be its pixels)."""
        if not self.current():
            raise DecodeError("frames: this pose's staged frames were reused by another capture "
                              "before the decode read them; decode the pose again from its "
                              "frame store")

    def done(self) -> None:
        """Tell the capture side this reader needs the buffer no more, and remove the sidecar
        (the capture side leaves it to the reader) unless a later capture of the pose wrote
        its own."""
        if self.current():
            self.header[_READER_DONE] = 1
        try:
            mine = json.loads(self.sidecar.read_text())["token"] == self.token.hex()
        except (OSError, ValueError, KeyError, TypeError):
            return
        if mine:
            self.sidecar.unlink(missing_ok=True)

    def close(self) -> None:
        """Drop this reader's views (the mapping stays with `READER_MAPS`)."""
        self.frames = self.header = np.empty(0, np.uint8)
