"""Write an uncompressed NPZ (a stored zip of .npy members) fast and durably: the layout is
known from the arrays' sizes, so members are written in parallel at their offsets straight
from the arrays' memory (no copy), their disk writeback starts as each lands, and the file
is fsynced and renamed into place (then its folder fsynced): never a partial file at `path`."""

from __future__ import annotations

import ctypes
import io
import os
import struct
import threading
import time
import zipfile
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from isal.isal_zlib import crc32

from calibration.shared.atomic import atomic_path, fsync_path

_SYNC_FILE_RANGE_WRITE = 2  # <fcntl.h>: start writeback of the range's dirty pages, no wait
_LIMIT = zipfile.ZIP64_LIMIT  # fields above this go in zip64 extras (as zipfile does)
_SEEK_LOCK = threading.Lock()  # seek + write where there is no pwrite


_ALIGN_ID = 0xD935  # extra-field record that pads a local header (zipalign's convention)


@dataclass
class NpyMember:
    """One .npy member: its name, the .npy header, the array data (None while only laid
    out) and where it lands."""

    name: bytes
    npy_header: bytes
    nbytes: int  # of the array data
    data: memoryview | None = None
    offset: int = 0  # of the local file header
    crc: int = 0
    stamp: tuple[int, int] = (0, 0x21)  # MS-DOS time and date (1980-01-01 00:00)
    pad: int = 0  # bytes of the local header's alignment record (0: none)

    @property
    def size(self) -> int:
        return len(self.npy_header) + self.nbytes

    @property
    def data_at(self) -> int:
        """File offset of the array data (after the local and .npy headers)."""
        return self.offset + len(local_header(self)) + len(self.npy_header)


def npy_header(shape: tuple[int, ...], dtype: np.dtype) -> bytes:
    """The .npy (1.0) header of a C-order array: a multiple of 64 bytes, as NumPy writes it."""
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": np.lib.format.dtype_to_descr(dtype),
                                                "fortran_order": False, "shape": shape})
    return head.getvalue()


def npy_member(key: str, arr: np.ndarray) -> NpyMember:
    """`arr` as a .npy member (not laid out)."""
    if arr.dtype.hasobject:
        raise ValueError(f"{key}: object arrays cannot be stored without pickle")
    if not arr.flags.c_contiguous:  # (np.ascontiguousarray would make 0-d arrays 1-d)
        arr = np.ascontiguousarray(arr)
    return NpyMember(f"{key}.npy".encode(), npy_header(arr.shape, arr.dtype), arr.nbytes,
                   memoryview(arr.reshape(-1).view(np.uint8)))


def lay_out(members: list[NpyMember], start: int = 0, align: int = 1) -> int:
    """Place `members` one after another from `start`, each member's array data at a
    multiple of `align` (padding in its local header's extra field); returns the end."""
    t = time.localtime()
    stamp = (t.tm_hour << 11 | t.tm_min << 5 | t.tm_sec // 2,
             max(t.tm_year - 1980, 0) << 9 | t.tm_mon << 5 | t.tm_mday)
    offset = start
    for m in members:
        m.offset, m.stamp, m.pad = offset, stamp, 0
        pad = -m.data_at % align
        m.pad = pad + align * (0 < pad < 6)  # a record needs 6 bytes (id, size, alignment)
        offset = m.data_at + m.nbytes
    return offset


def _members(arrays: Mapping[str, np.ndarray]) -> list[NpyMember]:
    """The arrays as .npy members, laid out one after another from offset 0."""
    members = [npy_member(key, arr) for key, arr in arrays.items()]
    lay_out(members)
    return members


def local_header(m: NpyMember) -> bytes:
    """The local file header (always with a zip64 size extra, like `force_zip64`; then the
    alignment record, if any)."""
    extra = struct.pack("<HHQQ", 1, 16, m.size, m.size)
    if m.pad:
        extra += struct.pack("<HHH", _ALIGN_ID, m.pad - 4, 0) + bytes(m.pad - 6)
    return struct.pack(zipfile.structFileHeader, zipfile.stringFileHeader,
                       zipfile.ZIP64_VERSION, 0, 0, 0, *m.stamp, m.crc,
                       0xFFFFFFFF, 0xFFFFFFFF, len(m.name), len(extra)) + m.name + extra


def member_crc(m: NpyMember, data: memoryview | np.ndarray) -> int:
    """CRC-32 of the member: .npy header, then `data` (ISA-L's: zlib's CRC-32, ~10x faster
    with carry-less multiplies; it releases the GIL for large buffers)."""
    return crc32(data, crc32(m.npy_header))


def central_directory(members: list[NpyMember], start: int) -> bytes:
    """Central directory and end records (zip64 ones where sizes or offsets need them)."""
    out = []
    for m in members:
        extra = [v for v in (m.size, m.size) if m.size > _LIMIT]
        if m.offset > _LIMIT:
            extra.append(m.offset)
        ext = struct.pack(f"<HH{len(extra)}Q", 1, 8 * len(extra), *extra) if extra else b""
        size = 0xFFFFFFFF if m.size > _LIMIT else m.size
        version = zipfile.ZIP64_VERSION if extra else zipfile.DEFAULT_VERSION
        out.append(struct.pack(zipfile.structCentralDir, zipfile.stringCentralDir, version, 3,
                               version, 0, 0, 0, *m.stamp, m.crc, size, size, len(m.name),
                               len(ext), 0, 0, 0, 0o600 << 16,
                               min(m.offset, 0xFFFFFFFF)) + m.name + ext)
    cd = b"".join(out)
    n, size = len(members), len(cd)
    if n >= zipfile.ZIP_FILECOUNT_LIMIT or start > _LIMIT or size > _LIMIT:
        cd += struct.pack(zipfile.structEndArchive64, zipfile.stringEndArchive64, 44, 45, 45,
                          0, 0, n, n, size, start)
        cd += struct.pack(zipfile.structEndArchive64Locator, zipfile.stringEndArchive64Locator,
                          0, start + size, 1)
        n, size, start = min(n, 0xFFFF), min(size, 0xFFFFFFFF), min(start, 0xFFFFFFFF)
    return cd + struct.pack(zipfile.structEndArchive, zipfile.stringEndArchive, 0, 0, n, n,
                            size, start, 0)


def _start_writeback() -> Callable[[int, int, int], None]:
    """`sync_file_range(fd, offset, length, WRITE)` where libc has it (Linux), else a no-op:
    the disk starts on a member while the others are still being written."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).sync_file_range
    except (AttributeError, OSError, TypeError):  # no such function, no libc (Windows)
        return lambda fd, offset, length: None
    fn.argtypes = [ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint]
    return lambda fd, offset, length: fn(fd, offset, length, _SYNC_FILE_RANGE_WRITE) and None


def pwrite_all(fd: int, data: memoryview | bytes, offset: int) -> None:
    """Write every byte of `data` at `offset` (a write may be short); where the OS has no
    `pwrite` (Windows), seek and write under a lock."""
    view = memoryview(data)
    if not hasattr(os, "pwrite"):
        with _SEEK_LOCK:
            os.lseek(fd, offset, os.SEEK_SET)
            while view.nbytes:
                view = view[os.write(fd, view):]
        return
    while view.nbytes:
        n = os.pwrite(fd, view, offset)
        view, offset = view[n:], offset + n


def write_npz_stored(path: str | Path, arrays: Mapping[str, np.ndarray],
                     timings: dict[str, float] | None = None, *, durable: bool = True) -> None:
    """Write `arrays` to `path` as an uncompressed NPZ (np.load reads it), atomically and (with
    `durable`) fsynced with its folder entry; `timings` (if given) receives the wall seconds
    of "write" and "fsync". `durable=False`: the page cache only, for callers that fsync
    later (still renamed into place whole)."""
    t0 = time.perf_counter()
    members = _members(arrays)
    writeback = _start_writeback() if durable else (lambda fd, offset, length: None)
    target = Path(path)
    with atomic_path(target) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            def write(m: NpyMember) -> None:
                pwrite_all(fd, m.npy_header, m.data_at - len(m.npy_header))
                pwrite_all(fd, m.data, m.data_at)
                m.crc = member_crc(m, m.data)
                pwrite_all(fd, local_header(m), m.offset)
                writeback(fd, m.offset, m.data_at + m.nbytes - m.offset)

            order = sorted(members, key=lambda m: -m.size)  # largest first: balanced threads
            with ThreadPoolExecutor(min(os.cpu_count() or 1, 4),
                                    thread_name_prefix="npz-write") as pool:
                list(pool.map(write, order))
            end = members[-1].data_at + members[-1].nbytes
            pwrite_all(fd, central_directory(members, end), end)
            t1 = time.perf_counter()
            if durable:
                os.fsync(fd)
        finally:
            os.close(fd)
    if durable:
        fsync_path(target.resolve().parent)  # the rename
    if timings is not None:
        timings["write"], timings["fsync"] = t1 - t0, time.perf_counter() - t1
