"""`run_task` is written once (`TaskRunner`): tickets are tracked while a task is in flight,
cancel reaches the task's flag, progress reaches the job's callback, and a settled task is
forgotten; executors only say how to launch."""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future
from typing import Any

import pytest

from api.worker.executor import InProcessExecutor
from api.worker.task_runner import TaskRunner, Ticket
from calibration.shared.progress import Cancelled, TaskContext


def _until_cancelled(ctx: TaskContext, started: threading.Event) -> dict[str, Any]:
    ctx.progress(1, 2, "waiting")
    started.set()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        ctx.check_cancelled()
        time.sleep(0.005)
    return {"cancelled": False}


def test_in_process_run_task_progress_cancel_and_forget() -> None:
    ex = InProcessExecutor(max_workers=1)
    seen: list[tuple[int, int, str]] = []
    started = threading.Event()
    fut = ex.run_task(_until_cancelled, started, job_id="job_a",
                      on_progress=lambda d, t, s: seen.append((d, t, s)))
    assert started.wait(5)
    assert ex.ticket("job_a") is not None and seen == [(1, 2, "waiting")]
    assert ex.cancel("job_a")
    with pytest.raises(Cancelled):
        fut.result(5)
    assert ex.ticket("job_a") is None and not ex.cancel("job_a")
    ex.shutdown()


class _Immediate(TaskRunner):
    """A backend that runs the task inline: what a new executor has to write."""

    unique_jobs = True

    def _new_flag(self, job_id: str) -> threading.Event:
        return threading.Event()

    def _launch(self, task_fn: Any, ticket: Ticket, args: tuple[Any, ...],
                kwargs: dict[str, Any]) -> Future:
        self.inside = self.ticket(ticket.job_id) is ticket
        out: Future = Future()
        self.pending = out
        return out


def test_unique_jobs_refuse_a_second_task_until_the_first_settles() -> None:
    ex = _Immediate()
    first = ex.run_task(lambda ctx: {}, job_id="job_b")
    assert ex.inside
    with pytest.raises(ValueError, match="already running"):
        ex.run_task(lambda ctx: {}, job_id="job_b")
    first.set_result({})
    assert ex.tickets() == []
    ex.run_task(lambda ctx: {}, job_id="job_b")  # accepted again once the first one settled


def test_a_failed_launch_leaves_no_ticket() -> None:
    class Broken(_Immediate):
        def _launch(self, *a: Any) -> Future:
            raise OSError("scheduler gone")

    ex = Broken()
    with pytest.raises(OSError):
        ex.run_task(lambda ctx: {}, job_id="job_c")
    assert ex.tickets() == []
