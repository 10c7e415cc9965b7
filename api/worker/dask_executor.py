"""The Dask-backed executor: the same task functions as `InProcessExecutor`, on a cluster.

`DaskExecutor(address)` connects a `distributed.Client` to a scheduler (`tcp://host:8786`)
or starts a private `LocalCluster` for `local` / `local:N`. Every job-aware task runs in a
small wrapper on the worker that gives it a `TaskContext` whose

- `progress()` goes out through `Worker.log_event` on one topic that this client
  subscribes to once (`Client.subscribe_topic`) and routes to the job's callback;
- `cancelled()` reads a `distributed.Event` named after the job (set by `cancel`),
  polled at most every `cancel_poll_s` so tight loops do not flood the scheduler.

Results come back as `concurrent.futures.Future`s, so the service awaits both executors
the same way. Arguments are paths (data by reference): large arrays in `run_task`
arguments are refused. A worker that dies mid-task makes the scheduler re-run the task
elsewhere; after `distributed.scheduler.allowed-failures` deaths the job fails with
`WorkerLost`, which names the task and the reason, instead of hanging.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Mapping
from concurrent.futures import Future, InvalidStateError
from typing import Any

from api.worker.dask_context import PROGRESS_TOPIC, cancel_event_name, run_in_worker
from api.worker.task_runner import TaskRunner, Ticket
from calibration.extras import require
from calibration.shared.progress import Cancelled

LOCAL_PREFIX = "local"
DEFAULT_MAX_ARG_BYTES = 1 << 20


class WorkerLost(RuntimeError):
    """A task's worker died more often than the scheduler allows; the job failed."""


class _Job:
    """Client-side state of one submitted job; `set()` is its cancel flag.

    Cancel sets the job's `distributed.Event` (a running task sees `cancelled()`) and drops
    the task if no worker has started it yet.
    """

    def __init__(self, client: Any, job_id: str) -> None:
        self.client = client
        self.job_id = job_id
        self.started = False
        self.cancel_requested = False
        self.dask_future: Any = None
        self.future: Future = Future()

    def set(self) -> None:
        """Ask the job to stop."""
        from distributed import Event

        self.cancel_requested = True
        Event(cancel_event_name(self.job_id), client=self.client).set()
        if not self.started and self.dask_future is not None:
            self.client.cancel(self.dask_future)


def _parse_local(address: str) -> int | None:
    """Worker count of a `local` / `local:N` address; None for a scheduler address."""
    if not address.startswith(LOCAL_PREFIX):
        return None
    rest = address[len(LOCAL_PREFIX):]
    if rest == "":
        return 2
    if rest.startswith(":") and rest[1:].isdigit() and int(rest[1:]) > 0:
        return int(rest[1:])
    raise ValueError(f"executor address {address!r}: expected 'local' or 'local:N' with N >= 1")


def start_local_cluster(n_workers: int = 2) -> Any:
    """A loopback-only `LocalCluster` of single-threaded worker processes.

    The scheduler always serves HTTP (health, metrics, dashboard when bokeh is installed):
    bind it to a free loopback port so it neither clashes with a running cluster on 8787
    nor listens beyond 127.0.0.1.
    """
    require("dask", "a local Dask cluster")
    from distributed import LocalCluster

    return LocalCluster(
        n_workers=n_workers,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
    )


def _nbytes(value: Any) -> int:
    """Size of the array or buffer payload in an argument (one level into containers)."""
    if hasattr(value, "nbytes") and hasattr(value, "dtype"):
        return int(value.nbytes)
    if isinstance(value, bytes | bytearray | memoryview):
        return len(value)
    if isinstance(value, list | tuple):
        return sum(_nbytes(v) for v in value if not isinstance(v, list | tuple | dict))
    if isinstance(value, dict):
        return sum(_nbytes(v) for v in value.values() if not isinstance(v, list | tuple | dict))
    return 0


class DaskExecutor(TaskRunner):
    """Runs job tasks on a Dask cluster with progress, cooperative cancel and clean failure."""

    unique_jobs = True

    def __init__(
        self,
        address: str | Any,
        *,
        timeout_s: float = 10.0,
        cancel_poll_s: float = 0.2,
        progress_interval_s: float = 0.05,
        max_arg_bytes: int = DEFAULT_MAX_ARG_BYTES,
    ) -> None:
        require("dask", "the Dask executor")
        from distributed import Client

        super().__init__()
        self._cluster: Any = None
        if isinstance(address, Client):
            self.client = address
            self._owns_client = False
        else:
            n_local = _parse_local(str(address))
            target: Any = str(address)
            if n_local is not None:
                self._cluster = start_local_cluster(n_local)
                target = self._cluster
            try:
                self.client = Client(target, timeout=timeout_s, set_as_default=False)
            except OSError as exc:
                if self._cluster is not None:
                    self._cluster.close()
                raise ConnectionError(
                    f"Dask scheduler {address!r} did not answer within {timeout_s:g} s ({exc}); "
                    "start it with `dask scheduler` and workers with `dask worker ADDRESS`, "
                    "or unset PHASECAL_DASK to run jobs in-process"
                ) from exc
            self._owns_client = True
        self.cancel_poll_s = float(cancel_poll_s)
        self.progress_interval_s = float(progress_interval_s)
        self.max_arg_bytes = int(max_arg_bytes)
        self._closed = False
        self.client.subscribe_topic(PROGRESS_TOPIC, self._on_event)

    @property
    def address(self) -> str:
        """The scheduler address this executor submits to."""
        return str(self.client.scheduler.address)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        """Run a plain module-level callable on the cluster (no job context)."""
        self._check_open()
        dfut = self.client.submit(fn, *args, pure=False, **kwargs)
        out: Future = Future()
        out.set_running_or_notify_cancel()
        dfut.add_done_callback(lambda f: self._settle(out, f, getattr(fn, "__name__", "task")))
        return out

    def _admit(self, task_fn: Callable[..., Any], args: tuple[Any, ...],
               kwargs: dict[str, Any]) -> None:
        self._check_open()
        self._check_by_reference(task_fn, args, kwargs)

    def _new_flag(self, job_id: str) -> _Job:
        return _Job(self.client, job_id)

    def _launch(self, task_fn: Callable[..., Any], ticket: Ticket, args: tuple[Any, ...],
                kwargs: dict[str, Any]) -> Future:
        job: _Job = ticket.flag  # type: ignore[assignment]
        job.future.set_running_or_notify_cancel()
        name = getattr(task_fn, "__name__", "task")
        options = {"cancel_poll_s": self.cancel_poll_s, "progress_s": self.progress_interval_s}
        job.dask_future = self.client.submit(
            run_in_worker,
            task_fn,
            ticket.job_id,
            args,
            kwargs,
            options,
            key=f"phasecal-{name}-{ticket.job_id}-{uuid.uuid4().hex[:8]}",
            pure=False,
        )
        job.dask_future.add_done_callback(lambda f: self._finish(ticket, f, name))
        return job.future

    def running_jobs(self) -> list[str]:
        """Ids of jobs submitted and not finished yet."""
        return sorted(t.job_id for t in self.tickets())

    def shutdown(self, wait: bool = True) -> None:
        """Wait for every job, or (wait=False) flag them cancelled and fail their futures now;
        then close the client and any cluster this executor started."""
        if self._closed:
            return
        jobs: list[_Job] = [t.flag for t in self.tickets()]  # type: ignore[misc]
        for job in jobs:
            if wait:
                job.future.exception()
            else:
                job.set()
                _set_exception(job.future, Cancelled(
                    f"job {job.job_id}: the executor was shut down while it was active"))
        self._closed = True
        self.client.unsubscribe_topic(PROGRESS_TOPIC)
        if self._owns_client:
            self.client.close()
        if self._cluster is not None:
            self._cluster.close()

    def __enter__(self) -> DaskExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown(wait=exc[0] is None)

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("DaskExecutor was shut down; create a new one")

    def _check_by_reference(
        self, task_fn: Callable[..., Any], args: tuple[Any, ...], kwargs: Mapping[str, Any]
    ) -> None:
        """Refuse large in-memory arrays: workers read data from the shared store by path."""
        for where, value in [*((f"argument {i}", a) for i, a in enumerate(args)),
                             *((f"argument {k!r}", v) for k, v in kwargs.items())]:
            size = _nbytes(value)
            if size > self.max_arg_bytes:
                raise ValueError(
                    f"{getattr(task_fn, '__name__', 'task')}: {where} carries {size} bytes of "
                    f"array data (limit {self.max_arg_bytes}); write it to the data store and "
                    "pass its path so workers read it there"
                )

    def _on_event(self, event: tuple[float, Any]) -> None:
        """Route one progress/start message from a worker to its job's callback."""
        _stamp, msg = event
        if not isinstance(msg, dict):
            return
        ticket = self.ticket(str(msg.get("job_id")))
        if ticket is None:
            return
        if msg.get("kind") == "start":
            ticket.flag.started = True  # type: ignore[attr-defined]
        elif msg.get("kind") == "progress":
            ticket.report(msg["done"], msg["total"], msg["stage"])

    def _finish(self, ticket: Ticket, dfut: Any, name: str) -> None:
        """Forget the job, then settle its future from the Dask future."""
        job: _Job = ticket.flag  # type: ignore[assignment]
        self._forget(ticket)  # before settling: a waiter woken by the result sees it gone
        self._settle(job.future, dfut, name, job.job_id)
        if not job.cancel_requested:
            self._clear_event(job.job_id)

    def _clear_event(self, job_id: str) -> None:
        """Drop the job's (unset) flag from the scheduler once the job is over.

        A cancelled job keeps its flag set: a task dropped by `Client.cancel` may already be
        running on a worker and must still see `cancelled()` (one small entry per cancel).
        """
        from distributed import Event

        try:
            Event(cancel_event_name(job_id), client=self.client).clear()
        except Exception:  # the client may be closing; the flag dies with the scheduler
            return

    @staticmethod
    def _settle(out: Future, dfut: Any, name: str, job_id: str | None = None) -> None:
        """Copy a Dask future's outcome to a concurrent future, naming lost workers."""
        from distributed import KilledWorker

        what = f"{name} of job {job_id}" if job_id else name
        if dfut.status == "cancelled":
            _set_exception(out, Cancelled(f"{what} was cancelled before it started"))
            return
        try:
            exc = dfut.exception()
            value = dfut.result() if exc is None else None
        except Exception as err:  # the client lost the scheduler
            _set_exception(out, err)
            return
        if exc is None:
            try:
                out.set_result(value)
            except InvalidStateError:  # already failed by shutdown(wait=False)
                return
        elif isinstance(exc, KilledWorker):
            failed = WorkerLost(
                f"{what}: its worker died while running it ({exc}); the scheduler gave up "
                "after distributed.scheduler.allowed-failures attempts — check worker memory "
                "limits and logs"
            )
            failed.__cause__ = exc
            _set_exception(out, failed)
        else:
            _set_exception(out, exc)


def _set_exception(out: Future, exc: BaseException) -> None:
    """Fail a future unless it is already settled (shutdown and completion may race)."""
    try:
        out.set_exception(exc)
    except InvalidStateError:
        return


__all__ = ["DaskExecutor", "WorkerLost", "start_local_cluster"]
