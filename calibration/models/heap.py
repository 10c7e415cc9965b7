"""Keep freed memory in the process during a multi-million-pixel fit (glibc), then return it.

Why: a fit allocates and frees full-size arrays (tens of MB) and per-block temporaries many
times; glibc trims the freed top of its heaps right away, so the next allocation faults
every page in again. On the 1024x1024, 3-pose sGCC benchmark that was ~250k page faults and
1.7-3.5 s of system time (of ~10 s CPU); with the trim threshold raised for the fit, 115k
and 1.1-1.4 s. Afterwards the thresholds are set to what glibc's own dynamic tuning reaches
after freeing such arrays (mmap 32 MB, trim 64 MB) and malloc_trim hands the memory back.
A no-op where the C library is not glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
from collections.abc import Iterator
from contextlib import contextmanager

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # <malloc.h>
_MMAP_MAX = 32 << 20  # glibc's largest mmap threshold on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX)
_TRIM_DURING = 2**31 - 1  # (mallopt takes an int) in effect never trim while a fit runs
_TRIM_AFTER = 2 * _MMAP_MAX  # what the dynamic threshold reaches after a 32 MB free

_lock = threading.Lock()
_active = 0
_trims = 0  # how often the free heap went back to the system (`trims`)


def _libc() -> ctypes.CDLL | None:
    """glibc, or None (other C libraries have no mallopt/malloc_trim)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018 - raises AttributeError outside glibc
    except (OSError, AttributeError):
        return None
    return libc


_LIBC = _libc()


def trims() -> int:
    """How many times `retained_heap` has handed the free heap back to the system: a process
    that keeps a warm heap for its decodes (`calibration.decode.heap`) warms it again."""
    return _trims


@contextmanager
def retained_heap() -> Iterator[None]:
    """Within the block freed memory stays mapped (no heap trimming); nested and concurrent
    blocks share one setting, the last to leave returns the memory to the system."""
    global _active, _trims
    if _LIBC is None:
        yield
        return
    with _lock:
        if _active == 0:
            _LIBC.mallopt(_M_MMAP_THRESHOLD, _MMAP_MAX)
            _LIBC.mallopt(_M_TRIM_THRESHOLD, _TRIM_DURING)
        _active += 1
    try:
        yield
    finally:
        with _lock:
            _active -= 1
            if _active == 0:
                _LIBC.mallopt(_M_TRIM_THRESHOLD, _TRIM_AFTER)
                _LIBC.malloc_trim(0)
                _trims += 1
