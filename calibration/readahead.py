"""Start reading a pose's frames from disk before the decoder needs them (no imports beyond
the standard library, so `phasecal decode` can call it before loading NumPy and numba)."""

from __future__ import annotations

import os
from pathlib import Path


def prefetch(path: str | Path) -> None:
    """Ask the OS to read a frames file, or a folder's frame_* images, into the page cache in
    the background (POSIX_FADV_WILLNEED); a no-op where that is unavailable or fails."""
    if not hasattr(os, "posix_fadvise"):
        return
    p = Path(path)
    try:
        files = [f for f in p.iterdir() if f.name.startswith("frame_")] if p.is_dir() else [p]
    except OSError:
        return  # read_frames reports a missing or unreadable path
    for f in files:
        try:
            fd = os.open(f, os.O_RDONLY)
        except OSError:
            continue
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_WILLNEED)
        except OSError:
            pass  # a hint only
        finally:
            os.close(fd)
