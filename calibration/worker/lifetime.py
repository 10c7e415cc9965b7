"""Worker processes die with the server that started them, however it dies (kill -9 too).

Two independent guards, installed by `die_with_parent` as a process initializer:
Linux `prctl(PR_SET_PDEATHSIG, SIGKILL)` (the kernel kills the worker when the thread that
spawned it exits, so it is used only when that thread is the parent's main thread), and a
watchdog thread that exits the worker once its parent pid changes (any POSIX system).
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time

PR_SET_PDEATHSIG = 1
WATCHDOG_PERIOD_S = 0.25


def _set_pdeathsig() -> bool:
    """Ask the kernel to SIGKILL this process when its parent thread exits (Linux only)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch(parent_pid: int) -> None:
    while True:
        if os.getppid() != parent_pid:
            os._exit(1)  # the server is gone: never finish (or write) its work
        time.sleep(WATCHDOG_PERIOD_S)


def die_with_parent(parent_pid: int, use_pdeathsig: bool = True) -> None:
    """Process initializer: exit as soon as `parent_pid` is no longer this process's parent.
    A terminal's Ctrl-C reaches the whole process group: the worker ignores it and lets the
    server stop it in order (else each idle worker printed a KeyboardInterrupt traceback)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if use_pdeathsig:
        _set_pdeathsig()
    if os.getppid() != parent_pid:  # the parent died before the guards were in place
        os._exit(1)
    threading.Thread(target=_watch, args=(parent_pid,), name="phasecal-parent-watchdog",
                     daemon=True).start()


def guard_args() -> tuple[int, bool]:
    """`initargs` for `die_with_parent` from the process about to spawn workers.

    PDEATHSIG follows the spawning *thread*: safe only when the main thread spawns.
    """
    return os.getpid(), threading.current_thread() is threading.main_thread()
