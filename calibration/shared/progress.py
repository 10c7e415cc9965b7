"""The one progress/cancel vocabulary of phasecal, shared by the acquisition controller, the
fitters, the worker tasks and the service's jobs (it sits low so all of them can import it).

- `ProgressFn(done, total, stage)`: report `done` of `total` units of work in `stage`.
- `CancelCheck()`: True once the user asked to stop; `Cancel` also accepts a
  `threading.Event` or None (never cancelled), read with `is_cancelled`.
- `Cancelled`: raised by whatever noticed the request; the job ends as `cancelled`.
- `TaskContext`: what a running task sees of its job (both of the above, plus its id).
- `Progress`: a progress record with an ETA, for callers that want one object per report.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

ProgressFn = Callable[[int, int, str], None]
CancelCheck = Callable[[], bool]
Cancel = threading.Event | CancelCheck | None


class Cancelled(Exception):
    """The user cancelled the job, acquisition or fit that raises this."""


@dataclass(frozen=True)
class Progress:
    """Progress report: units done of total, estimated seconds left, stage name."""

    done: int
    total: int
    eta_s: float | None
    stage: str


def is_cancelled(cancel: Cancel) -> bool:
    """Whether a threading.Event is set or a check returns True (None: never)."""
    if cancel is None:
        return False
    if isinstance(cancel, threading.Event):
        return cancel.is_set()
    return bool(cancel())


def check_cancelled(cancel: Cancel, what: str) -> None:
    """Raise `Cancelled("<what> cancelled")` once `cancel` says so."""
    if is_cancelled(cancel):
        raise Cancelled(f"{what} cancelled")


class TaskContext:
    """What a running task sees of its job: report progress, poll for cancellation."""

    def __init__(
        self,
        job_id: str,
        on_progress: ProgressFn | None = None,
        cancel_event: threading.Event | None = None,
    ) -> None:
        self.job_id = job_id
        self._on_progress = on_progress
        self._cancel = cancel_event or threading.Event()

    def progress(self, done: int, total: int, stage: str) -> None:
        """Report `done` of `total` units in `stage` (forwarded to the job manager)."""
        if self._on_progress is not None:
            self._on_progress(int(done), int(total), str(stage))

    def cancelled(self) -> bool:
        """True once the job was asked to stop; tasks poll this between steps."""
        return self._cancel.is_set()

    def check_cancelled(self) -> None:
        """Raise `Cancelled` if the job was asked to stop."""
        if self.cancelled():
            raise Cancelled(f"job {self.job_id} was cancelled")
