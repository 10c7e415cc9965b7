"""The executor interface every heavy job of the service goes through.

Task functions are module-level callables `fn(ctx: TaskContext, *args, **kwargs) -> dict`
(see `api.worker.tasks`): they take file paths, write their outputs atomically
and return a small JSON-able summary, so they can run in a thread or on a Dask worker.
`InProcessExecutor` runs them on a thread pool (NumPy/SciPy/OpenCV release the GIL);
`make_executor("tcp://...")` returns the Dask-backed executor of
`api.worker.dask_executor`.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from multiprocessing.connection import wait as wait_ready
from multiprocessing.managers import SyncManager
from typing import Any, Protocol, runtime_checkable

from api.worker.lifetime import (
    die_with_parent,
    guard_args,
    one_blas_thread,
    restore_blas_threads,
)
from api.worker.task_runner import TaskRunner, Ticket
from calibration import one_heap_arena, warm_up
from calibration.shared.progress import ProgressFn, TaskContext

DASK_ENV = "PHASECAL_DASK"
WARM_ENV = "PHASECAL_WARM_KERNELS"  # "0": worker processes leave the kernels to their first decode


@runtime_checkable
class Executor(Protocol):
    """Shaped like `concurrent.futures.Executor`, plus job-aware submission and cancel."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future: ...

    def run_task(
        self,
        task_fn: Callable[..., Any],
        /,
        *args: Any,
        job_id: str,
        on_progress: ProgressFn | None = None,
        **kwargs: Any,
    ) -> Future: ...

    def cancel(self, job_id: str) -> bool: ...

    def shutdown(self, wait: bool = True) -> None: ...


class InProcessExecutor(TaskRunner):
    """Runs tasks on a thread pool in this process; cancel sets the task's flag."""

    def __init__(self, max_workers: int | None = None) -> None:
        super().__init__()
        workers = max_workers or max(1, min(4, os.cpu_count() or 1))
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="phasecal-task")

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        """Run a plain callable on the pool."""
        return self._pool.submit(fn, *args, **kwargs)

    def _new_flag(self, job_id: str) -> threading.Event:
        return threading.Event()

    def _launch(self, task_fn: Callable[..., Any], ticket: Ticket, args: tuple[Any, ...],
                kwargs: dict[str, Any]) -> Future:
        ctx = TaskContext(ticket.job_id, ticket.on_progress, ticket.flag)  # type: ignore[arg-type]
        return self._pool.submit(task_fn, ctx, *args, **kwargs)

    def shutdown(self, wait: bool = True) -> None:
        """Stop accepting work; flag every running task as cancelled when not waiting."""
        if not wait:
            self.cancel_all()
        self._pool.shutdown(wait=wait, cancel_futures=not wait)


_FORGET = "__forget__"
#: what talking to a manager process that is gone raises (refused, reset, no socket, EOF)
MANAGER_GONE = (OSError, EOFError)

log = logging.getLogger("phasecal.worker")
KILL_WAIT_S = 5.0  # how long a shutdown waits for the workers it killed to be gone


class _RemoteContext(TaskContext):
    """A `TaskContext` inside a worker process: progress goes through a queue."""

    def __init__(self, job_id: str, queue: Any, cancel_event: Any) -> None:
        super().__init__(job_id, None, None)
        self._queue = queue
        self._remote_cancel = cancel_event

    def progress(self, done: int, total: int, stage: str) -> None:
        self._queue.put((self.job_id, int(done), int(total), str(stage)))

    def cancelled(self) -> bool:
        return bool(self._remote_cancel.is_set())


def _run_remote(task_fn: Callable[..., Any], job_id: str, queue: Any, cancel_event: Any,
                args: tuple[Any, ...], kwargs: dict[str, Any]) -> Any:
    """Worker-process entry: build the context and run the task."""
    return task_fn(_RemoteContext(job_id, queue, cancel_event), *args, **kwargs)


def start_worker(parent_pid: int, use_pdeathsig: bool, warm_kernels: bool,
                 blas_threads: int = 1) -> None:
    """Worker-process initializer: the lifetime guards (`die_with_parent`), the worker's
    `blas_threads` BLAS threads (spawned with one: `lifetime.one_blas_thread`), then, with
    `warm_kernels`, a daemon thread that loads the decoder's compiled kernels while the
    worker waits for its first task, so its first live decode does not pay the load
    (~0.4 CPU s from numba's cache) while that pose's frames arrive."""
    die_with_parent(parent_pid, use_pdeathsig)  # first: it needs a process of one thread
    restore_blas_threads(blas_threads)
    if warm_kernels:
        threading.Thread(target=warm_kernels_quietly, name="phasecal-warm-kernels",
                         daemon=True).start()


def warm_kernels_quietly() -> None:
    """`warm_up`, logging a failure (the first decode then loads the kernels itself and
    reports what is wrong) instead of ending the thread with a traceback on stderr."""
    try:
        warm_up()
    except Exception:
        log.warning("loading the decoder's kernels ahead of the first decode failed",
                    exc_info=True)


class ManagedFlag:
    """A job's cancel flag kept by the manager process (`event`, what the worker polls).

    Setting it once the manager is gone does nothing: no worker can read it any more, and a
    shutdown that cancels every job must reach the next one."""

    def __init__(self, event: Any) -> None:
        self.event = event

    def set(self) -> None:
        """Set the managed event (a no-op when the manager is gone)."""
        try:
            self.event.set()
        except MANAGER_GONE:
            pass


class ProcessExecutor(TaskRunner):
    """Runs tasks in worker processes (spawned), so GIL-bound numerics never stall the API.

    Workers and the manager process exit when this process dies (`worker.lifetime`), and
    ignore the stop signals sent to the whole service so that `shutdown` stops them in order.

    Progress comes back through a managed queue drained by one thread; cancel flips a
    managed event the task polls through `TaskContext.cancelled()`.
    """

    #: seconds `shutdown(wait=False)` gives cancelled tasks to return before their workers
    #: are killed (a task in a long step that does not poll its cancel flag)
    stop_grace_s = 5.0

    def __init__(self, max_workers: int | None = None, warm_kernels: bool = False) -> None:
        """`warm_kernels`: each worker loads the decoder's compiled kernels in the background
        as it starts (`start_worker`; `make_executor("processes")`, the service's, does)."""
        super().__init__()
        ctx = mp.get_context("spawn")
        workers = max_workers or max(1, min(2, os.cpu_count() or 1))
        guard = guard_args()  # workers and the manager die with this process (kill -9 too)
        # workers start with one BLAS thread (until their SIGTERM is blocked) and one heap
        # arena (a rig's concurrent decodes keep their freed memory: `one_heap_arena`)
        with one_blas_thread() as blas_threads, one_heap_arena():
            self._pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx,
                                             initializer=start_worker,
                                             initargs=(*guard, warm_kernels, blas_threads))
            # Spawn every worker now, from this thread: PDEATHSIG follows the spawning
            # thread, and a worker spawned lazily by a short-lived job thread would die
            # with it.
            before = set(mp.active_children())
            self._pool._launch_processes()
            self._workers = [p for p in mp.active_children() if p not in before]
            # A first task starts the pool's manager thread (spawning nothing more: every
            # worker exists); without it shutdown() and interpreter exit never stop them.
            self._pool.submit(os.getpid).result()
            self._manager = SyncManager(ctx=ctx)
            self._manager.start(die_with_parent, guard)
        self._queue = self._manager.Queue()
        self._callbacks: dict[str, ProgressFn] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._drain = threading.Thread(target=self._forward, name="phasecal-progress",
                                       daemon=True)
        self._drain.start()

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        """Run a picklable callable in a worker process."""
        return self._pool.submit(fn, *args, **kwargs)

    def _new_flag(self, job_id: str) -> ManagedFlag:
        return ManagedFlag(self._manager.Event())

    def _launch(self, task_fn: Callable[..., Any], ticket: Ticket, args: tuple[Any, ...],
                kwargs: dict[str, Any]) -> Future:
        if ticket.on_progress is not None:
            with self._lock:
                self._callbacks[ticket.job_id] = ticket.on_progress
        event = ticket.flag.event  # type: ignore[attr-defined]
        return self._pool.submit(_run_remote, task_fn, ticket.job_id, self._queue, event,
                                 args, kwargs)

    def shutdown(self, wait: bool = True) -> None:
        """Stop the workers, the progress thread and the manager; a second call does nothing.

        Without waiting, running tasks are flagged cancelled and a worker still busy after
        `stop_grace_s` is killed, so no worker outlives this call. A worker or a manager
        that already died (killed with the service's process group) is no error."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if not wait:
            self.cancel_all()
        try:
            self._pool.shutdown(wait=wait, cancel_futures=not wait)
        except Exception:  # a broken pool must not keep the manager running
            log.warning("stopping the worker pool failed", exc_info=True)
        if not wait:
            self._end_workers(self.stop_grace_s)
        try:
            self._queue.put(None)
        except MANAGER_GONE:
            pass  # the progress thread sees the manager gone and returns by itself
        self._drain.join(5)
        self._manager.shutdown()  # asks, then terminates, then kills; a dead one is no error

    def _end_workers(self, grace_s: float) -> None:
        """Wait up to `grace_s` for the workers to exit; kill those still running (the pool's
        own thread reaps them)."""
        running = {}
        for p in self._workers:
            try:
                running[p.sentinel] = p  # readable once the process has exited
            except ValueError:  # closed: long gone
                continue
        deadline = time.monotonic() + grace_s
        while running and time.monotonic() < deadline:
            for sentinel in wait_ready(list(running), max(0.0, deadline - time.monotonic())):
                running.pop(sentinel)
        for p in running.values():
            log.warning("worker process %s did not stop within %.0f s: killed", p.pid, grace_s)
            p.kill()
        if running:  # gone when this returns (a SIGKILL takes a moment on a loaded machine)
            wait_ready(list(running), KILL_WAIT_S)

    def _forward(self) -> None:
        """Deliver progress in order; a job's callback is dropped after its last report."""
        while True:
            try:
                item = self._queue.get()
            except MANAGER_GONE:  # the manager is gone (shutdown, interpreter exit)
                return
            if item is None:
                return
            if item[0] == _FORGET:
                with self._lock:
                    self._callbacks.pop(item[1], None)
                continue
            job_id, done, total, stage = item
            cb = self._callbacks.get(job_id)
            if cb is not None:
                try:
                    cb(done, total, stage)
                except Exception:  # one job's failing callback must not end the others'
                    log.exception("progress of job %s not delivered", job_id)

    def _settled(self, ticket: Ticket) -> None:
        # The worker queued all its progress before returning, so this marker comes last.
        if self._closed:
            return  # the progress thread is stopped or stopping: nothing left to deliver
        try:
            self._queue.put((_FORGET, ticket.job_id))
        except MANAGER_GONE:
            pass


def make_executor(address: str | None = None) -> Executor:
    """Threads (default), worker processes ("processes", loading the decoder's kernels as
    they start unless env PHASECAL_WARM_KERNELS is "0"), or Dask for `tcp://...`.

    The address comes from the argument or env PHASECAL_DASK.
    """
    address = address or os.environ.get(DASK_ENV) or None
    if address is None or address in ("inprocess", "threads"):
        return InProcessExecutor()
    if address == "processes":  # the service's workers: each loads the kernels as it starts
        return ProcessExecutor(warm_kernels=os.environ.get(WARM_ENV, "1") != "0")
    if not address.startswith(("tcp://", "tls://", "inproc://", "local")):
        raise ValueError(
            f"executor address {address!r}: expected 'tcp://host:port' of a Dask scheduler, "
            f"'processes', or unset {DASK_ENV} for the in-process threads"
        )
    from api.worker.dask_executor import DaskExecutor  # lazy: the optional dask extra

    return DaskExecutor(address)
