"""The one atomic file writer: write a temporary file in the target's folder, fsync, rename
over the target, so readers never see a half-written file (and a crash leaves the old one)."""

from __future__ import annotations

import errno
import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path next to `path` (same suffix, so writers that pick the format from the
    extension still work) that replaces `path` when the block succeeds; removed if it fails."""
    p = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.stem}.", suffix=p.suffix, dir=p.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def fsync_path(path: str | Path) -> None:
    """fsync a file, or a folder (its entries: creations and renames); a folder is skipped
    where folders cannot be opened (not POSIX)."""
    p = Path(path)
    if os.name != "posix" and p.is_dir():
        return
    fd = os.open(p, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_file(path: str | Path) -> Iterator[BinaryIO]:
    """A binary file to write `path` through: flushed, fsynced and renamed over `path` when
    the block succeeds, removed if it fails."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        yield fh
        fh.flush()
        os.fsync(fh.fileno())


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` atomically (fsync before the rename)."""
    with atomic_file(path) as fh:
        fh.write(data)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write UTF-8 `text` to `path` atomically."""
    write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | Path, data: Any, *, indent: int = 1) -> None:
    """Write `data` as JSON (no NaN/Infinity: they are not JSON) plus a newline, atomically."""
    write_text_atomic(path, json.dumps(data, indent=indent, allow_nan=False) + "\n")


def allocate(fd: int, size: int) -> None:
    """Give an open file `size` bytes of real blocks (fallocate, or zeros written where the
    filesystem cannot), so that writes into it cannot fail later for lack of space: a full
    disk then shows when the file is made, not halfway through filling it."""
    try:
        os.posix_fallocate(fd, 0, size)
        return
    except OSError as exc:
        if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
            raise
    chunk = bytes(1 << 20)
    done = 0
    while done < size:
        done += os.pwrite(fd, chunk[: min(len(chunk), size - done)], done)
