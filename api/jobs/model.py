"""The job vocabulary: status and kind enums, the typed job state, and `Job`, the base of
every job definition (what a kind of job runs and how its outcome lands on its resource)."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from enum import StrEnum
from typing import Any, ClassVar

from sqlalchemy.orm import Session

from api.db import JobRecord
from calibration.shared.progress import TaskContext


class JobStatus(StrEnum):
    """Where a job is: queued -> running -> succeeded | failed | cancelled | interrupted."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"
    INTERRUPTED = "interrupted"  # cut off by a server stop or restart


class JobKind(StrEnum):
    """What a job does (the API's job `kind`)."""

    CAPTURE = "capture"
    DECODE = "decode"
    CALIBRATE = "calibrate"
    INTRINSICS = "intrinsics"
    HANDEYE = "handeye"
    AUTO = "auto"  # the closed loop: a robot places, phasecal plans, captures, refits


ACTIVE_JOB_STATES = (JobStatus.QUEUED.value, JobStatus.RUNNING.value)
TERMINAL_JOB_STATES = tuple(s.value for s in JobStatus if s.value not in ACTIVE_JOB_STATES)
STOPPED_STATES = (JobStatus.CANCELLED.value, JobStatus.INTERRUPTED.value)


@dataclass
class JobState:
    """A job as the API shows it (the `Job` schema): status, stage, progress and outcome."""

    id: str
    kind: str
    status: str = JobStatus.QUEUED.value
    stage: str = JobStatus.QUEUED.value
    done: int = 0
    total: int = 0
    eta_s: float | None = None
    resource: str | None = None
    session_id: str | None = None
    error: str | None = None
    result: dict[str, Any] | None = None
    created_at: float = field(default_factory=time.time)
    started_at: float | None = None
    finished_at: float | None = None

    #: the fields a job row stores and updates while the job runs
    STORED: ClassVar[tuple[str, ...]] = ("status", "stage", "done", "total", "error", "result",
                                         "started_at", "finished_at")

    @classmethod
    def from_record(cls, rec: JobRecord) -> JobState:
        """The state of a stored job (no ETA: it is measured only while a job runs here)."""
        return cls(id=rec.id, kind=rec.kind, status=rec.status, stage=rec.stage, done=rec.done,
                   total=rec.total, resource=rec.resource, session_id=rec.session_id,
                   error=rec.error, result=rec.result, created_at=rec.created_at,
                   started_at=rec.started_at, finished_at=rec.finished_at)

    def to_record(self, row: JobRecord) -> None:
        """Copy the fields that change while a job runs onto its row."""
        for key in self.STORED:
            setattr(row, key, getattr(self, key))

    def to_dict(self) -> dict[str, Any]:
        """Plain data (the API's `Job` body)."""
        return asdict(self)

    def copy(self, **changes: Any) -> JobState:
        """A copy with some fields changed."""
        return replace(self, **changes)


@dataclass(kw_only=True)
class Job:
    """A job definition: subclasses set `kind`, hold what the job needs, and implement `run`.

    `claims`: ids of the poses/calibrations the job works on (one active job each, a 409
    otherwise); the lock rows are written in the job's own transaction and deleted in its
    final one. `succeeded`/`ended` update the job's resource in that final transaction.
    """

    kind: ClassVar[JobKind]
    resource: str | None = None
    session_id: str | None = None
    claims: tuple[str, ...] = ()
    total: int = 0

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        """Do the work (on the job's driver thread); the result is the job's `result`."""
        raise NotImplementedError

    def succeeded(self, s: Session, result: dict[str, Any]) -> None:
        """Update the resource for a successful outcome (in the job's final transaction)."""

    def ended(self, s: Session, status: str, error: str) -> None:
        """Update the resource for a job that failed, was cancelled or was interrupted."""
