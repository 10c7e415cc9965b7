"""A pose's maps file laid out before its decode, so the decoder writes into it directly.

The array members of a pose's maps (docs/formats.md) (x, y float64; sigma, modulation, blur
float32; mask bool) have shapes known once the camera's shape and the plan's axes are. The
live decode creates the stored NPZ with every array member's data at a page-aligned offset
before the first frame (`MapsFile`), its pages are faulted in while frames arrive
(`calibration.prefault`), and the decoder's outputs are views of the file's pages
(`outputs`). After the decode only the CRC-32s, the local headers, `meta` and the central
directory are written (`commit`) and the file is renamed into place whole: no copy of
~200 MB of maps and no page faults after the last frame. A long-lived worker lays the file
out in a resident buffer instead (`resident=True`, `resident_buffers`): the file's image is
then written from it with O_DIRECT (no page-cache pages to fault in, pose after pose: seconds
of CPU on a VM for a 4-camera rig), the rows the decoder reports final while it finishes the
rest (`write_rows`), what is left at the commit, and the buffer serves the next decode
(`recycle`).
A failed or cancelled decode removes the temporary file (`close`); np.load reads the result
like any NPZ (docs/formats.md). POSIX: the file is renamed while the decoder's views of it may
still be mapped.
"""

from __future__ import annotations

import errno
import mmap
import os
import tempfile
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calibration.prefault import IdlePrefault
from calibration.shared.atomic import fsync_path
from calibration.shared.npz_store import (
    NpyMember,
    central_directory,
    lay_out,
    local_header,
    member_crc,
    npy_header,
    npy_member,
    pwrite_all,
)
from calibration.shared.resident_buffers import RESIDENT

if TYPE_CHECKING:
    from calibration.shared.maps import DecodedMaps

_PAGE = mmap.PAGESIZE
_BLOCK = 4096  # O_DIRECT writes whole blocks


def _aligned(size: int) -> int:
    return -(-size // _BLOCK) * _BLOCK
# the decoder's (2, npix) output planes and the members of their rows x, y
PLANES = {"position": ("x", "y"), "sigma": ("sigma_x", "sigma_y"),
          "modulation": ("modulation_x", "modulation_y"), "blur": ("blur_x", "blur_y")}


_F64, _F32 = np.dtype(np.float64), np.dtype(np.float32)
# the array members in `DecodedMaps.npz_arrays` order (docs/formats.md dtypes)
_DTYPES = {"x": _F64, "y": _F64, "sigma_x": _F32, "sigma_y": _F32, "mask": np.dtype(bool),
           "modulation_x": _F32, "modulation_y": _F32, "blur_x": _F32, "blur_y": _F32}


def _layout(shape: tuple[int, int], axes: list[str]) -> dict[str, NpyMember]:
    """The array members of a pose's maps (blur only for the plan's axes), each array's data
    page-aligned, laid out from offset 0."""
    npix = shape[0] * shape[1]
    members = {key: NpyMember(f"{key}.npy".encode(), npy_header(shape, dt), dt.itemsize * npix)
               for key, dt in _DTYPES.items() if not key.startswith("blur_") or key[-1] in axes}
    lay_out(list(members.values()), align=_PAGE)
    return members


def warm_resident(shape: tuple[int, int], axes: list[str], count: int) -> None:
    """Have this process keep `count` resident buffers for maps of `shape` and `axes`, their
    pages faulted in now (a worker warming up for a rig's cameras, while a capture runs)."""
    last = list(_layout((int(shape[0]), int(shape[1])), list(axes)).values())[-1]
    size = _aligned(last.data_at + last.nbytes)
    buffers = [RESIDENT.take(size) for _ in range(count)]
    for buf in buffers:
        np.frombuffer(buf, np.uint8)[::_PAGE] = 0
    for buf in buffers:
        RESIDENT.give(buf)


class MapsFile:
    """The maps NPZ of one decode, created at `path`'s hidden temporary name and renamed to
    `path` by `commit`; its disk space is reserved at once (a full disk fails here, before
    any frame is decoded, never with a SIGBUS on a mapped page)."""

    def __init__(self, path: str | Path, shape: tuple[int, int], axes: list[str], *,
                 resident: bool = False) -> None:
        self.path = Path(path)
        self.shape = (int(shape[0]), int(shape[1]))
        self.axes = list(axes)
        self._members = _layout(self.shape, self.axes)
        last = list(self._members.values())[-1]
        self._end = last.data_at + last.nbytes  # where `meta` and the directory go
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=self.path.suffix,
                                   dir=self.path.parent)
        self._fd, self._tmp, self._done = fd, Path(tmp), False
        self._mm: mmap.mmap | None = None
        self._buffer: mmap.mmap | None = None  # the resident buffer, until `recycle`
        self._direct: int | None = None  # its O_DIRECT descriptor (-1: refused; None: not yet)
        self._written: dict[str, int] = {}  # bytes of each member's data on disk (`write_rows`)
        try:
            self._reserve(_aligned(self._end) if resident else self._end)
            if resident:
                self._mm = self._buffer = RESIDENT.take(_aligned(self._end))
            else:
                self._mm = mmap.mmap(fd, self._end)
            self._bytes = np.frombuffer(self._mm, np.uint8)
            for m in self._members.values():
                self._mm[m.data_at - len(m.npy_header):m.data_at] = m.npy_header
        except BaseException:
            self.close()
            raise

    @property
    def mapped(self) -> np.ndarray:
        """The file's bytes up to `meta` (uint8, writable): to fault in ahead of the decoder
        (`calibration.prefault.IdlePrefault`)."""
        return self._bytes

    def _reserve(self, size: int) -> None:
        """Allocate the array members' disk blocks (`posix_fallocate`; a sparse file where the
        OS has none): ENOSPC here is a clear error, not a SIGBUS on a mapped page later."""
        try:
            if hasattr(os, "posix_fallocate"):
                os.posix_fallocate(self._fd, 0, size)
            else:
                os.ftruncate(self._fd, size)
        except OSError as exc:
            raise OSError(exc.errno, f"cannot reserve {size / 1e6:.0f} MB for the maps "
                          f"({exc.strerror})", str(self.path)) from None

    def outputs(self) -> dict[str, np.ndarray] | None:
        """The decoder's outputs as views of the file: (2, npix) planes (rows x, y; the row
        stride is the distance between the two members) and the flat bool "mask"; None when
        the plan lacks an axis (its blur has no member to write into)."""
        if self._mm is None or any(a not in self.axes for a in ("x", "y")):
            return None
        npix = self.shape[0] * self.shape[1]
        out = {}
        for plane, (kx, ky) in PLANES.items():
            mx, my, dtype = self._members[kx], self._members[ky], _DTYPES[kx]
            out[plane] = np.ndarray((2, npix), dtype=dtype, buffer=self._mm, offset=mx.data_at,
                                    strides=(my.data_at - mx.data_at, dtype.itemsize))
        out["mask"] = self._view("mask").reshape(-1)
        return out

    def _view(self, key: str) -> np.ndarray:
        """Member `key`'s array data as its (H, W) array of the file's pages."""
        m = self._members[key]
        return self._bytes[m.data_at:m.data_at + m.nbytes].view(_DTYPES[key]).reshape(self.shape)

    def write_rows(self, rows: int) -> None:
        """Write the leading `rows` rows of every member (whole disk blocks) from the resident
        buffer now, while the decoder fills the rest (`StreamingDecoder.finish`'s
        `final_rows`): the commit writes only what is left, the last rows and the headers,
        not the whole 205 MB of a 5 MP pose after its finish. Nothing for a mapped file (its
        pages are the file's)."""
        if self._buffer is None or self._mm is None:
            return
        width = self.shape[1]
        for key, m in self._members.items():
            done = self._written.get(key, 0)
            upto = rows * width * _DTYPES[key].itemsize // _BLOCK * _BLOCK
            if upto > done:  # (data starts page-aligned: whole blocks from there)
                self._write_blocks(m.data_at + done, m.data_at + upto)
                self._written[key] = upto

    def commit(self, maps: DecodedMaps, *, durable: bool = True,
               timings: dict[str, float] | None = None) -> None:
        """Complete the file with `maps` and rename it to `path`: arrays that are not already
        the file's views (`outputs`) are copied in, the members' CRC-32s computed in threads,
        then the local headers, `meta` and the central directory written. `durable`: fsync
        the file before the rename and the folder after (False: the caller makes it durable
        later). The maps' arrays that are views of the file become read-only. `timings` (if
        given) receives the wall seconds of "write" and "fsync"."""
        t0 = time.perf_counter()
        arrays = maps.npz_arrays()
        meta = arrays.pop("meta")
        if list(arrays) != list(self._members):
            raise ValueError(f"maps members {list(arrays)} differ from the laid-out "
                             f"{list(self._members)} (shape {self.shape}, axes {self.axes})")
        assert self._mm is not None, "commit after close"
        views = []
        for key, arr in arrays.items():
            view = self._view(key)
            if arr.shape != view.shape or arr.dtype != view.dtype:
                raise ValueError(f"maps {key}: {arr.dtype} {arr.shape}, the file has "
                                 f"{view.dtype} {view.shape}")
            if arr.ctypes.data != view.ctypes.data or not arr.flags.c_contiguous:
                np.copyto(view, arr)
                self._written.pop(key, None)  # (its blocks on disk are stale now)
            else:
                views.append(arr)
        order = sorted(self._members.values(), key=lambda m: -m.nbytes)  # balanced threads

        def crc(m: NpyMember) -> None:
            m.crc = member_crc(m, self._bytes[m.data_at:m.data_at + m.nbytes])

        with ThreadPoolExecutor(min(os.cpu_count() or 1, 4), thread_name_prefix="maps-crc") as pool:
            list(pool.map(crc, order))
        for m in self._members.values():
            header = local_header(m)
            self._mm[m.offset:m.offset + len(header)] = header
        tail = npy_member("meta", meta)
        lay_out([tail], start=self._end)
        tail.crc = member_crc(tail, tail.data)
        end = tail.data_at + tail.nbytes
        members = [*self._members.values(), tail]
        if self._buffer is not None:
            self._write_image()
        last = (local_header(tail) + tail.npy_header + bytes(tail.data)
                + central_directory(members, end))
        pwrite_all(self._fd, last, tail.offset)
        if self._buffer is not None:  # (the image was written in whole disk blocks)
            os.ftruncate(self._fd, tail.offset + len(last))
        t1 = time.perf_counter()
        if durable:
            if self._buffer is None:
                self._mm.flush()
            os.fsync(self._fd)
        t2 = time.perf_counter()
        for arr in views:  # they are the committed file's pages now
            arr.flags.writeable = False
        os.replace(self._tmp, self.path)
        self._done = True
        self.close()
        if durable:
            fsync_path(self.path.resolve().parent)
        if timings is not None:
            timings["write"], timings["fsync"] = t1 - t0, t2 - t1

    def _write_image(self) -> None:
        """Write the resident buffer's image of the file up to `meta` (whole 4 KiB blocks),
        less the blocks `write_rows` wrote: the headers and each member's rest."""
        at = 0
        for key, m in self._members.items():  # (in file order)
            done = self._written.get(key, 0)
            if done:
                self._write_blocks(at, m.data_at)
                at = m.data_at + done
        self._write_blocks(at, _aligned(self._end))

    def _write_blocks(self, start: int, stop: int) -> None:
        """Write bytes [start, stop) (block-aligned) of the resident buffer to the file with
        O_DIRECT, or through the page cache where the filesystem refuses it."""
        if stop <= start:
            return
        assert self._buffer is not None
        image = memoryview(self._buffer)[start:stop]
        if self._direct is None:
            try:
                self._direct = os.open(self._tmp, os.O_WRONLY | os.O_DIRECT)
            except (OSError, AttributeError):  # (tmpfs; a system without O_DIRECT)
                self._direct = -1
        if self._direct >= 0:
            try:
                pwrite_all(self._direct, image, start)
                return
            except OSError as exc:
                if exc.errno != errno.EINVAL:
                    raise
                os.close(self._direct)
                self._direct = -1
        pwrite_all(self._fd, image, start)

    def recycle(self) -> None:
        """Give the resident buffer to this process's next decode (after `close` or `commit`,
        once no view of the outputs or of the committed maps is used again)."""
        if self._buffer is not None and self._mm is None:
            RESIDENT.give(self._buffer)
            self._buffer = None

    def close(self) -> None:
        """Release the mapping and the descriptor; remove the temporary file unless committed
        (views still alive keep their pages mapped until they go; a resident buffer is kept
        for `recycle`, else dropped with the last view)."""
        if self._mm is not None:
            self._bytes = np.empty(0, np.uint8)
            if self._buffer is None:
                try:
                    self._mm.close()
                except BufferError:  # the caller still holds views: unmapped when they go
                    pass
            self._mm = None
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        if self._direct is not None and self._direct >= 0:
            os.close(self._direct)
        self._direct = None
        if not self._done:
            self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> MapsFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()



@contextmanager
def prefaulted(out: MapsFile) -> Iterator[IdlePrefault]:
    """The decode's output set up once for every path that decodes into a laid-out maps file
    (a live pose's worker, `phasecal decode`): `out` open for the decoder while a thread at
    idle priority faults its pages in (first-touch faults: ~0.5 CPU s at 5 MP), so the
    finish writes into resident memory."""
    with out, IdlePrefault([out.mapped]) as ahead:
        yield ahead
