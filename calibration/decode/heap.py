"""Freed heap memory kept, and faulted in ahead, in a long-lived decoding process (glibc).

By default glibc maps each block of >= 128 KB afresh and unmaps it when freed, and gives
the heap's free top back to the OS beyond 128 KB, so the finish's temporaries (the noise
sample, the line fit, the reason codes) are new pages on every pose: ~13000-16000 page
faults per 5 MP finish, and on a VM each first touch costs ~2-3 ms of CPU per MB (~0.15 CPU
s per finish), while unmapping takes the address space's lock that the other threads'
page faults wait on. `retain_freed_memory` serves blocks up to `MMAP_MAX` from the heap and
keeps up to `TRIM_MAX` of free heap per arena: from a worker's second pose on, a finish
takes ~20 faults. `warm_heap` also faults in, before the frames arrive, what the first
pose's finish would take (~0.04 CPU s, huge pages), and keeps that much free heap; again
after a fit in the same process handed the free heap back (`models.heap.retained_heap`),
else that worker's next pose faults it in after its last frame.

A process decoding several cameras at once (a rig's, a thread each) runs in one heap arena
(`one_heap_arena`, set in its environment before it starts): glibc gives other threads
arenas of 64 MB heaps, and deletes a heap that becomes wholly free whatever the trim
threshold, so four concurrent 5 MP finishes faulted in 7000-40000 new pages on every pose
(0.3-1.3 CPU s of system time on this VM); in one arena, with the free heap of four
finishes kept, ~30.
"""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import os
import sys
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from calibration.models.heap import trims

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc <malloc.h>
MMAP_MAX = 32 << 20  # glibc's own ceiling for its adaptive threshold
TRIM_MAX = 256 << 20
# What a 5 MP finish's first run faulted in, with room for the accumulation's blocks that
# stay allocated between (measured: 160 MB leaves ~800 faults; 48 MB ~8000).
MAIN_WARM, THREAD_WARM = 160 << 20, 16 << 20
_warmed = 0  # decoding threads whose heap arenas were faulted in
_warmed_at = 0  # `models.heap.trims()` then: a fit since handed that heap back
_warming = threading.Lock()  # (a rig's camera threads ask at once)
_keep_for = 1  # the most finishes at once this process has run
ARENA_VAR = "MALLOC_ARENA_MAX"  # glibc's arena count, read once as a process starts


@contextlib.contextmanager
def one_heap_arena() -> Iterator[None]:
    """Processes started inside run in one glibc heap arena (the environment they inherit),
    unless the variable was already set (the user's choice stands)."""
    if ARENA_VAR in os.environ:
        yield
        return
    os.environ[ARENA_VAR] = "1"
    try:
        yield
    finally:
        os.environ.pop(ARENA_VAR, None)


@functools.lru_cache(maxsize=1)
def _mallopt() -> Any:
    """glibc's `mallopt`, or None where the C library is not glibc."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        return None
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt


def retain_freed_memory(decodes: int = 1) -> bool:
    """Set the thresholds, keeping the free heap of as many finishes at once as this
    process has run (`decodes`, or more before); set at every decode, since a fit's
    `calibration.models.heap.retained_heap` sets its own when it ends. False where the C
    library is not glibc."""
    global _keep_for
    mallopt = _mallopt()
    if mallopt is None:
        return False
    _keep_for = max(_keep_for, decodes)
    # (glibc trims all of a free top larger than the threshold: room above what is warmed)
    return (bool(mallopt(M_MMAP_THRESHOLD, MMAP_MAX))
            and bool(mallopt(M_TRIM_THRESHOLD, TRIM_MAX + (_keep_for - 1) * MAIN_WARM)))


def _touch(nbytes: int) -> None:
    """Allocate `nbytes` from this thread's heap in blocks it serves, write every page and
    free them: kept (`retain_freed_memory`), they serve the next allocations."""
    piece = MMAP_MAX // 2
    blocks = [np.ones(min(piece, nbytes - at), dtype=np.uint8) for at in range(0, nbytes, piece)]
    del blocks


def warm_heap(decodes: int = 1) -> bool:
    """Once per process (glibc only): keep freed memory, and fault in the heap pages a
    5 MP finish uses, in this thread and in each thread of the decode pool (each has its
    own heap arena, unless the process runs in one: `one_heap_arena`); with `decodes` > 1
    (a rig's cameras, each finished on a thread of its own) in as many threads at once, so
    as many arenas are warm, and as much free heap is kept (the free heap of four
    concurrent finishes outgrows `TRIM_MAX`: `retain_freed_memory`). True if done now."""
    with _warming:
        return _warm_heap(decodes)


def _warm_heap(decodes: int) -> bool:
    """`warm_heap`, under its lock."""
    global _warmed, _warmed_at
    if trims() != _warmed_at:  # a fit in this process returned the free heap: warm it again
        _warmed, _warmed_at = 0, trims()
    if not retain_freed_memory(decodes) or _warmed >= decodes:
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
