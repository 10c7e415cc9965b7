"""`run_task` written once for every executor (threads, worker processes, Dask).

An executor says how to start a task on its backend (`_launch`) and what a job's cancel
flag is (`_new_flag`); `TaskRunner.run_task` does the rest the same way everywhere: track
the job's ticket (flag + progress callback), launch, forget the ticket when the task's
future settles, and answer `cancel(job_id)` by setting the flag.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Protocol

from calibration.shared.progress import ProgressFn


class Flag(Protocol):
    """A job's cancel flag: a `threading.Event`, a managed or a Dask event, ..."""

    def set(self) -> Any: ...


@dataclass(eq=False)
class Ticket:
    """One submitted task of a job: its id, progress callback and cancel flag."""

    job_id: str
    on_progress: ProgressFn | None
    flag: Flag

    def report(self, done: int, total: int, stage: str) -> None:
        """Forward a progress report to the job's callback (if any)."""
        if self.on_progress is not None:
            self.on_progress(int(done), int(total), str(stage))


class TaskRunner:
    """Base of the executors: job-aware submission, cancel and bookkeeping, written once."""

    #: refuse a second task for a job id that still has one in flight (else the new one
    #: replaces the old one's ticket)
    unique_jobs = False

    def __init__(self) -> None:
        self._tickets: dict[str, Ticket] = {}
        self._tickets_lock = threading.Lock()

    # -- what an executor provides ----------------------------------------------------
    def _new_flag(self, job_id: str) -> Flag:
        """The cancel flag of a new task of job `job_id`."""
        raise NotImplementedError

    def _launch(self, task_fn: Callable[..., Any], ticket: Ticket, args: tuple[Any, ...],
                kwargs: dict[str, Any]) -> Future:
        """Start `task_fn(ctx, *args, **kwargs)` on the backend; its future."""
        raise NotImplementedError

    def _admit(self, task_fn: Callable[..., Any], args: tuple[Any, ...],
               kwargs: dict[str, Any]) -> None:
        """Refuse a task before anything is tracked (default: accept)."""

    def _settled(self, ticket: Ticket) -> None:
        """Called once the task's future settled, after its ticket is forgotten."""

    # -- the one implementation ------------------------------------------------------
    def run_task(
        self,
        task_fn: Callable[..., Any],
        /,
        *args: Any,
        job_id: str,
        on_progress: ProgressFn | None = None,
        **kwargs: Any,
    ) -> Future:
        """Run `task_fn(TaskContext, *args, **kwargs)` for job `job_id`; its future."""
        self._admit(task_fn, args, kwargs)
        ticket = Ticket(job_id, on_progress, self._new_flag(job_id))
        with self._tickets_lock:
            if self.unique_jobs and job_id in self._tickets:
                raise ValueError(f"job {job_id!r} is already running (one task per job id)")
            self._tickets[job_id] = ticket
        try:
            fut = self._launch(task_fn, ticket, args, dict(kwargs))
        except BaseException:
            self._forget(ticket)
            raise
        fut.add_done_callback(lambda _f: (self._forget(ticket), self._settled(ticket)))
        return fut

    def cancel(self, job_id: str) -> bool:
        """Ask the task of `job_id` to stop; False if no such task is queued or running."""
        ticket = self.ticket(job_id)
        if ticket is None:
            return False
        ticket.flag.set()
        return True

    def ticket(self, job_id: str) -> Ticket | None:
        """The in-flight task of `job_id`, if any."""
        with self._tickets_lock:
            return self._tickets.get(job_id)

    def tickets(self) -> list[Ticket]:
        """Every task in flight."""
        with self._tickets_lock:
            return list(self._tickets.values())

    def cancel_all(self) -> None:
        """Set every in-flight task's flag (shutdown without waiting)."""
        for ticket in self.tickets():
            ticket.flag.set()

    def _forget(self, ticket: Ticket) -> None:
        """Stop tracking the ticket, unless a newer task of the same job replaced it."""
        with self._tickets_lock:
            if self._tickets.get(ticket.job_id) is ticket:
                del self._tickets[ticket.job_id]
