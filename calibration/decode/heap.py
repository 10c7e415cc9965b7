"""Freed heap memory kept, and faulted in ahead, in a long-lived decoding process (glibc).

By default glibc maps each block of >= 128 KB afresh and unmaps it when freed, and gives
the heap's free top back to the OS beyond 128 KB, so the finish's temporaries (the noise
sample, the line fit, the reason codes) are new pages on every pose: ~13000-16000 page
faults per 5 MP finish, and on a VM each first touch costs ~2-3 ms of CPU per MB (~0.15 CPU
s per finish), while unmapping takes the address space's lock that the other threads'
page faults wait on. `retain_freed_memory` serves blocks up to `MMAP_MAX` from the heap and
keeps up to `TRIM_MAX` of free heap per arena: from a worker's second pose on, a finish
takes ~20 faults. `warm_heap` also faults in, before the frames arrive, what the first
pose's finish would take (~0.04 CPU s, huge pages).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc <malloc.h>
MMAP_MAX = 32 << 20  # glibc's own ceiling for its adaptive threshold
TRIM_MAX = 256 << 20
# What a 5 MP finish's first run faulted in, with room for the accumulation's blocks that
# stay allocated between (measured: 160 MB leaves ~800 faults; 48 MB ~8000).
MAIN_WARM, THREAD_WARM = 160 << 20, 16 << 20
_warmed = 0  # decoding threads whose heap arenas were faulted in


@functools.lru_cache(maxsize=1)
def retain_freed_memory() -> bool:
    """Set the thresholds once per process; False where the C library is not glibc."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_MAX)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_MAX))


def _touch(nbytes: int) -> None:
    """Allocate `nbytes` from this thread's heap in blocks it serves, write every page and
    free them: kept (`retain_freed_memory`), they serve the next allocations."""
    piece = MMAP_MAX // 2
    blocks = [np.ones(min(piece, nbytes - at), dtype=np.uint8) for at in range(0, nbytes, piece)]
    del blocks


def warm_heap(decodes: int = 1) -> bool:
    """Once per process (glibc only): keep freed memory, and fault in the heap pages a
    5 MP finish uses, in this thread and in each thread of the decode pool (each has its
    own heap arena); with `decodes` > 1 (a rig's cameras, each finished on a thread of its
    own) in as many threads at once, so as many arenas are warm. True if done now."""
    global _warmed
    if _warmed >= decodes or not retain_freed_memory():
        return False
    from calibration.decode.batch import pool

    if decodes > 1:
        together = threading.Barrier(decodes)

        def arena(_: int) -> None:
            try:  # (at once: each thread takes an arena of its own)
                together.wait(timeout=2.0)
            except threading.BrokenBarrierError:
                pass
            _touch(MAIN_WARM)

        with ThreadPoolExecutor(decodes, thread_name_prefix="warm-heap") as threads:
            list(threads.map(arena, range(decodes)))
    else:
        _touch(MAIN_WARM)
    if _warmed:
        _warmed = decodes
        return True
    workers = min(os.cpu_count() or 1, 4)  # (the pool's size)
    meet = threading.Barrier(workers)

    def one(_: int) -> None:
        try:  # one item per pool thread
            meet.wait(timeout=2.0)
        except threading.BrokenBarrierError:
            pass
        _touch(THREAD_WARM)

    list(pool().map(one, range(workers)))
    _warmed = decodes
    return True
