"""Worker side of `DaskExecutor`: a `TaskContext` whose progress and cancel cross the cluster.

Progress messages go to the scheduler with `Worker.log_event` on `PROGRESS_TOPIC` (the
executor's client subscribes once and routes them by job id); the cancel flag is the
`distributed.Event` named `cancel_event_name(job_id)`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from calibration.shared.progress import TaskContext

PROGRESS_TOPIC = "phasecal-progress"


def cancel_event_name(job_id: str) -> str:
    """Name of the `distributed.Event` that flags job `job_id` as cancelled."""
    return f"phasecal-cancel-{job_id}"


class DaskTaskContext(TaskContext):
    """TaskContext for a task running on a Dask worker."""

    def __init__(self, job_id: str, worker: Any, cancel_poll_s: float, progress_s: float) -> None:
        super().__init__(job_id)
        self._worker = worker
        self._cancel_poll_s = cancel_poll_s
        self._progress_s = progress_s
        self._event: Any = None
        self._cancel_seen = False
        self._next_poll = 0.0
        self._last_sent = 0.0
        self._last_stage: str | None = None

    def emit(self, kind: str, **fields: Any) -> None:
        """Send one message about this job to the executor's client."""
        self._worker.log_event(PROGRESS_TOPIC, {"job_id": self.job_id, "kind": kind, **fields})

    def progress(self, done: int, total: int, stage: str) -> None:
        """Forward progress, at most every `progress_s` except stage changes and completion."""
        now = time.monotonic()
        if stage == self._last_stage and done < total and now - self._last_sent < self._progress_s:
            return
        self._last_sent = now
        self._last_stage = stage
        self.emit("progress", done=int(done), total=int(total), stage=str(stage))

    def cancelled(self) -> bool:
        """True once the job's cancel Event is set (polled at most every `cancel_poll_s`)."""
        if self._cancel_seen:
            return True
        now = time.monotonic()
        if now < self._next_poll:
            return False
        self._next_poll = now + self._cancel_poll_s
        if self._event is None:
            from distributed import Event, get_client

            self._event = Event(cancel_event_name(self.job_id), client=get_client())
        self._cancel_seen = bool(self._event.is_set())
        return self._cancel_seen


def run_in_worker(
    task_fn: Callable[..., Any],
    job_id: str,
    args: tuple[Any, ...],
    kwargs: dict[str, Any],
    options: dict[str, float],
) -> Any:
    """Run `task_fn(ctx, *args, **kwargs)` on this worker with a cluster-aware context."""
    from distributed import get_worker

    ctx = DaskTaskContext(
        job_id, get_worker(), float(options["cancel_poll_s"]), float(options["progress_s"])
    )
    ctx.emit("start")
    ctx.check_cancelled()
    return task_fn(ctx, *args, **kwargs)


__all__ = ["PROGRESS_TOPIC", "DaskTaskContext", "cancel_event_name", "run_in_worker"]
