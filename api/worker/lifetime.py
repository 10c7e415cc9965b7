"""Worker processes die with the server that started them, however it dies (kill -9 too),
and stop only when that server says so.

Two independent guards, installed by `die_with_parent` as a process initializer:
Linux `prctl(PR_SET_PDEATHSIG, SIGKILL)` (the kernel kills the worker when the thread that
spawned it exits, so it is used only when that thread is the parent's main thread), and a
watchdog thread that exits the worker once its parent pid changes (any POSIX system).

Stop signals meant for the service are not the workers' to act on: a terminal's Ctrl-C
(SIGINT to the process group) and systemd's stop (SIGTERM to every process of the unit)
reach the workers at the same moment as the server. A worker that died then would fail the
job it runs (and its cancel flags with the manager) before the server could stop it in
order, so workers ignore SIGINT, and SIGTERM unless their parent sent it (the process pool
terminates a broken pool's workers with SIGTERM and must still be obeyed).

Taking SIGTERM by sender needs it blocked in every thread of the worker, which holds only
for threads started after the initializer: a worker imports NumPy before it (the spawned
process re-imports the server's main module), and OpenBLAS starts its threads at load, one
per core, with SIGTERM open. So workers are spawned with one BLAS thread
(`one_blas_thread`) and get their BLAS threads back once SIGTERM is blocked
(`restore_blas_threads`): without that, on any machine of more than one core, a stop of
the whole service killed the workers mid-task.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator

PR_SET_PDEATHSIG = 1
WATCHDOG_PERIOD_S = 0.25
BLAS_THREADS_VAR = "OPENBLAS_NUM_THREADS"


@contextlib.contextmanager
def one_blas_thread() -> Iterator[int]:
    """Processes spawned inside start with one OpenBLAS thread (the environment they
    inherit); yields the BLAS threads this process's children are meant to have (the
    variable's value where it was set, else one per core) for `restore_blas_threads`."""
    before = os.environ.get(BLAS_THREADS_VAR)
    wanted = int(before) if before and before.isdigit() else (os.cpu_count() or 1)
    os.environ[BLAS_THREADS_VAR] = "1"
    try:
        yield wanted
    finally:
        if before is None:
            del os.environ[BLAS_THREADS_VAR]
        else:
            os.environ[BLAS_THREADS_VAR] = before


def restore_blas_threads(count: int) -> None:
    """Give this process `count` BLAS threads again, started now from this thread (so with
    its signal mask)."""
    if count > 1:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=count, user_api="blas")


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


def _only_one_thread() -> bool:
    """True when this process runs a single thread (so a signal mask set now is everyone's:
    threads started later inherit it). Unknown (no /proc) counts as more than one."""
    try:
        return len(os.listdir("/proc/self/task")) == 1
    except OSError:
        return False


def _obey_sigterm_from(parent_pid: int) -> bool:
    """Leave SIGTERM to a thread that ends the process only when `parent_pid` sent it.

    The signal is blocked (in this thread and so in every thread started after) and taken
    with `sigwaitinfo`, which names the sender. Needs sigwaitinfo and a process of one
    thread; False (SIGTERM keeps its default action) otherwise.
    """
    if not hasattr(signal, "sigwaitinfo") or not _only_one_thread():
        return False
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    threading.Thread(target=_take_sigterm, args=(parent_pid,), name="phasecal-sigterm",
                     daemon=True).start()
    return True


def _take_sigterm(parent_pid: int) -> None:
    while True:
        info = signal.sigwaitinfo({signal.SIGTERM})
        if info.si_pid == parent_pid:
            # The server's own terminate(): SIGTERM's default action (the disposition was
            # never changed), as it expects; unblocked in this thread only, raised to it.
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
            signal.raise_signal(signal.SIGTERM)
            os._exit(128 + signal.SIGTERM)  # (not reached: a handler was installed)
        # anyone else's: the server got it too and stops this worker in order


def die_with_parent(parent_pid: int, use_pdeathsig: bool = True) -> None:
    """Process initializer: exit as soon as `parent_pid` is no longer this process's parent;
    ignore stop signals sent to the whole service (see the module's doc)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # else each worker printed a traceback
    _obey_sigterm_from(parent_pid)
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
