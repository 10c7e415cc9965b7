"""Fault a writable file mapping's pages in ahead of their use, at idle CPU priority.

On a VM, memory touched for the first time costs ~1.5-3 ms of CPU per MB (page cache pages
the guest allocates anew): ~0.5 CPU s for a 5 MP pose's 205 MB of maps. `IdlePrefault` pays
it before the pages are written, on CPU time nothing else wants (`SCHED_IDLE` where the OS
has it), with `madvise(MADV_POPULATE_WRITE)` through ctypes (no GIL held; Linux >= 5.14;
elsewhere each page is touched). Populating never changes a page's contents. Only for
mappings this process alone writes: an idle thread holding a page lock of a file another
process writes could hold that process up.
"""

from __future__ import annotations

import ctypes
import errno
import functools
import mmap
import os
import sys
import threading
from typing import Any

import numpy as np

PAGE = mmap.PAGESIZE
POPULATE_WRITE = 23 if sys.platform == "linux" else None  # MADV_POPULATE_WRITE


@functools.lru_cache(maxsize=1)
def _libc_madvise() -> Any:
    """libc's madvise through ctypes (which releases the GIL for the call), or None."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).madvise
    except (AttributeError, OSError, TypeError):  # no libc (Windows)
        return None
    fn.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    return fn


def _madvise(view: np.ndarray, start: int, length: int) -> bool:
    """madvise(MADV_POPULATE_WRITE) over `view[start:start + length]` (page-aligned); False
    where the kernel or the OS does not know it. Other errors (EFAULT: the file cannot back
    a page, e.g. a full disk; ENOMEM) raise."""
    fn = _libc_madvise()
    if POPULATE_WRITE is None or fn is None:
        return False
    if fn(view.ctypes.data + start, length, POPULATE_WRITE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(err, f"cannot fault in mapped pages ({os.strerror(err)})")


def populate(view: np.ndarray, start: int, length: int) -> None:
    """Fault in `view[start:start + length]` (a writable uint8 view of a shared mapping,
    `start` on a page), writable: madvise where it works, else write each page's first byte
    back."""
    if not _madvise(view, start, length):
        pages = view[start:start + length:PAGE]
        pages[...] = pages.copy()  # a write fault per page, contents unchanged


class IdlePrefault:
    """Fault in `regions` (writable uint8 views of shared mappings), in order, in
    `piece`-sized steps from a background thread at idle priority; `stop` ends it. Pieces
    are small (256 KB, ~0.5 ms of CPU) because madvise holds the process's mmap lock for
    reading meanwhile: an idle thread preempted there would make the process's next
    mmap/munmap (a large NumPy allocation) wait for idle CPU time."""

    def __init__(self, regions: list[np.ndarray], piece: int = 1 << 18) -> None:
        self.regions = regions
        self.piece = -(-piece // PAGE) * PAGE
        self.done = 0  # bytes faulted in, over all regions
        self.total = sum(view.nbytes for view in regions)
        self._stop = threading.Event()
        self._tid: int | None = None
        self._error: OSError | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> IdlePrefault:
        self._thread = threading.Thread(target=self._run, name="prefault", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        self._tid = threading.get_native_id()
        if hasattr(os, "SCHED_IDLE"):
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))  # this thread only
        try:
            for view in self.regions:
                for start in range(0, view.nbytes, self.piece):
                    if self._stop.is_set():
                        return
                    populate(view, start, min(self.piece, view.nbytes - start))
                    self.done += min(self.piece, view.nbytes - start)
        except OSError as exc:  # reported by `stop`
            self._error = exc

    def stop(self) -> None:
        """End the thread after its current piece, run at normal priority again (whoever
        waits on a page or lock that an idle thread holds must not wait for idle CPU);
        raise its error, if any. Idempotent."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stop.set()
        if self._tid is not None and hasattr(os, "SCHED_OTHER"):
            try:
                os.sched_setscheduler(self._tid, os.SCHED_OTHER, os.sched_param(0))
            except OSError:  # (the thread has ended)
                pass
        thread.join()
        if self._error is not None:
            raise self._error

    def __enter__(self) -> IdlePrefault:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        try:
            self.stop()
        except OSError:
            if exc[0] is None:  # (an error already on its way is not masked by this one)
                raise
