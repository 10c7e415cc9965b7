"""Job manager: runs `Job` definitions with state, progress, ETA, cancel and events.

States: queued -> running -> succeeded | failed | cancelled; jobs found active at
startup become `interrupted` (with the reason). Each job runs a small driver on its
own thread that waits on executor futures (numerics) or drives the camera (capture),
so the event loop never blocks. Progress lives in memory while a job runs (cheap to
poll) and is written to SQLite at most every `PERSIST_INTERVAL_S`.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import delete, event, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from api.db import Database, JobLockRecord, JobRecord
from api.jobs.model import ACTIVE_JOB_STATES, Job, JobState, JobStatus
from api.problems import Problem
from api.storage import DiskSpace, is_no_space
from api.store import new_id
from api.worker.executor import Executor
from calibration.shared.progress import Cancelled, TaskContext

log = logging.getLogger("phasecal.jobs")

PERSIST_INTERVAL_S = 0.5
RECENT_CAPACITY = 2048  # finished jobs answered from memory (status polls after the end)

@dataclass
class _Live:
    """In-memory state of a running job."""

    record: JobState
    cancel: threading.Event = field(default_factory=threading.Event)
    stage_started: float = field(default_factory=time.monotonic)
    stage_done0: int = 0
    persisted_at: float = 0.0
    subscribers: list[asyncio.Queue] = field(default_factory=list)
    seq: int = 0  # events published so far: the SSE event id (resume with Last-Event-ID)


class JobManager:
    """Creates, runs, tracks, cancels and recovers jobs; publishes events to SSE listeners.

    A route validates its request, builds a `Job` definition, `create`s it in the same
    transaction as the resource it works on, and `start`s it once that transaction
    committed.
    """

    def __init__(self, db: Database, executor: Executor, space: DiskSpace | None = None) -> None:
        self.db = db
        self.executor = executor
        self.space = space  # the data directory's reserve: outcomes are stored on a full disk
        self._live: dict[str, _Live] = {}
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._threads: list[threading.Thread] = []
        self._stopping = False
        self._recent: OrderedDict[str, dict[str, Any]] = OrderedDict()

    def bind_loop(self, loop: asyncio.AbstractEventLoop) -> None:
        """The event loop SSE subscribers live on (set at app startup)."""
        self._loop = loop

    # -- lifecycle -------------------------------------------------------------------
    def recover(self, reason: str) -> list[str]:
        """Mark every job left queued/running by a previous process as interrupted."""
        now = time.time()
        with self.db.session() as s:
            recs = s.scalars(select(JobRecord).where(JobRecord.status.in_(ACTIVE_JOB_STATES)))
            ids = []
            for rec in recs:
                rec.status = JobStatus.INTERRUPTED.value
                rec.error = reason
                rec.finished_at = now
                ids.append(rec.id)
            s.execute(delete(JobLockRecord))
        return ids

    def create(self, s: Session, job: Job) -> JobState:
        """Insert `job` queued, with its claims, in the caller's transaction (started later
        with `start`). A resource already claimed by an active job is a 409 (enforced by
        the job_locks primary key)."""
        state = JobState(id=new_id("job"), kind=job.kind.value, total=job.total,
                         resource=job.resource, session_id=job.session_id)
        rec = JobRecord(id=state.id, kind=state.kind, status=state.status, stage=state.stage,
                        done=0, total=state.total, resource=state.resource,
                        session_id=state.session_id, created_at=state.created_at)
        claims = job.claims
        for key in claims:
            held = s.get(JobLockRecord, key)
            if held is not None:
                raise Problem(409, "job-active", f"{key} is in use by active job {held.job_id}; "
                              "wait for it or cancel it", job_id=held.job_id)
        s.add(rec)
        s.add_all(JobLockRecord(key=key, job_id=rec.id) for key in claims)
        try:
            s.flush()
        except IntegrityError:
            raise Problem(409, "job-active", f"{', '.join(claims)}: another job was started "
                          "on it at the same time") from None
        with self._lock:
            self._live[rec.id] = _Live(state)
        # A route whose transaction fails after this point never starts the job: forget it.
        event.listen(s, "after_rollback", lambda _s: self._forget(rec.id), once=True)
        return state.copy()

    def _forget(self, job_id: str) -> None:
        """Drop a created-but-never-started job whose transaction rolled back."""
        with self._lock:
            live = self._live.get(job_id)
            if live is not None and live.record.status == JobStatus.QUEUED.value:
                self._live.pop(job_id)

    def start(self, job_id: str, job: Job) -> dict[str, Any]:
        """Run `job` (created with `create`) on a driver thread; the job as the API shows it."""
        live = self._live[job_id]
        ctx = TaskContext(job_id, lambda d, t, st: self.progress(job_id, d, t, st), live.cancel)
        th = threading.Thread(target=self._drive, args=(job_id, job, ctx),
                              name=f"job-{job_id}", daemon=True)
        self._threads = [t for t in self._threads if t.is_alive()] + [th]
        th.start()
        return self.get(job_id) or live.record.to_dict()

    def _drive(self, job_id: str, job: Job, ctx: TaskContext) -> None:
        try:
            self._set(job_id, status=JobStatus.RUNNING.value, started_at=time.time(),
                      stage="starting")
            ctx.check_cancelled()
            result = job.run(ctx)
        except Cancelled:
            self._finish(job_id, job, *self._stop_reason())
        except Exception as exc:  # every failure of a job is reported on the job
            if self._live[job_id].cancel.is_set():
                self._finish(job_id, job, *self._stop_reason())
            else:
                log.info("job %s failed", job_id, exc_info=True)
                self._finish(job_id, job, JobStatus.FAILED.value, self._reason(exc))
        else:
            self._finish(job_id, job, JobStatus.SUCCEEDED.value, None, result)

    def _reason(self, exc: BaseException) -> str:
        """A failed job's reason: one line, naming the lack of space when that was it."""
        if self.space is not None and is_no_space(exc):
            return self.space.no_space_reason(exc)
        return _describe(exc)

    def _storing(self, write: Callable[[], None]) -> None:
        """Run a database write; on a full disk with the reserve released and once more."""
        if self.space is None:
            write()
        else:
            self.space.retrying(write)

    def _stop_reason(self) -> tuple[str, str]:
        """(status, reason) of a job stopped by cancel or by the server shutting down."""
        if self._stopping:
            return (JobStatus.INTERRUPTED.value,
                    "interrupted: the server shut down while this job was active")
        return JobStatus.CANCELLED.value, "cancelled on request"

    def _finish(self, job_id: str, job: Job, status: str, error: str | None,
                result: dict[str, Any] | None = None) -> None:
        """Store the outcome, update the resource and drop the claims in one transaction."""
        live = self._live[job_id]
        # The in-memory record (what GET /jobs serves) takes the final state only after the
        # commit: a client seeing "succeeded" must find the resource updated too.
        final = live.record.copy(status=status, error=error, result=result,
                                 finished_at=time.time(), stage=status, eta_s=None)

        def store(state: JobState, hook: bool) -> None:
            with self.db.session() as s:
                if hook and state.status == JobStatus.SUCCEEDED:
                    job.succeeded(s, state.result or {})
                elif hook:
                    job.ended(s, state.status, state.error or "")
                self._write(s, job_id, state)
                s.execute(delete(JobLockRecord).where(JobLockRecord.job_id == job_id))

        try:
            self._storing(lambda: store(final, True))
        except Exception as exc:  # a failing hook or a full disk must still end the job
            log.exception("finishing job %s failed", job_id)
            why = self._reason(exc) if is_no_space(exc) else _describe(exc)
            final = live.record.copy(status=JobStatus.FAILED.value,
                                     error=f"could not store the job's outcome: {why}",
                                     finished_at=time.time(), stage=JobStatus.FAILED.value,
                                     eta_s=None)
            for hook in (True, False):  # the resource too if it can be, else the job alone
                try:
                    self._storing(lambda hook=hook: store(final, hook))
                    break
                except Exception:
                    log.exception("storing the failure of job %s failed (hook %s)", job_id, hook)
        live.record = final
        with self._lock:
            self._recent[job_id] = final.to_dict()
            while len(self._recent) > RECENT_CAPACITY:
                self._recent.popitem(last=False)
        self._publish(job_id, "end")
        with self._lock:
            self._live.pop(job_id, None)

    # -- progress & cancel -----------------------------------------------------------
    def progress(self, job_id: str, done: int, total: int, stage: str) -> None:
        """Record progress (called from worker threads); persisted at a bounded rate."""
        live = self._live.get(job_id)
        if live is None:
            return
        rec = live.record
        now = time.monotonic()
        if stage != rec.stage:
            live.stage_started, live.stage_done0 = now, done
        rec.done, rec.total, rec.stage = done, total, stage
        if now - live.persisted_at >= PERSIST_INTERVAL_S:
            live.persisted_at = now
            try:
                with self.db.session() as s:
                    self._write(s, job_id, rec)
            except Exception as exc:  # progress lives in memory; the outcome is stored later
                if not is_no_space(exc):
                    raise
                log.warning("job %s: progress not stored (no space left)", job_id)
        self._publish(job_id, "progress")

    def cancel(self, job_id: str) -> bool:
        """Ask a queued/running job to stop; False if it is not active in this process."""
        live = self._live.get(job_id)
        if live is None:
            return False
        live.cancel.set()
        self.executor.cancel(job_id)
        return True

    def is_cancelled(self, job_id: str) -> bool:
        """True when cancel was requested for a live job."""
        live = self._live.get(job_id)
        return live is not None and live.cancel.is_set()

    # -- reading ---------------------------------------------------------------------
    def snapshot(self, job_id: str) -> dict[str, Any] | None:
        """The live state with ETA, or None if the job is not running in this process."""
        live = self._live.get(job_id)
        if live is None:
            return None
        return live.record.copy(eta_s=_eta(live)).to_dict()

    def cached(self, job_id: str) -> dict[str, Any] | None:
        """The state from memory (live, or finished recently in this process), else None."""
        snap = self.snapshot(job_id)
        if snap is not None:
            return snap
        done = self._recent.get(job_id)
        return dict(done) if done is not None else None

    def get(self, job_id: str) -> dict[str, Any] | None:
        """From memory if possible, else the stored record; None if unknown."""
        cached = self.cached(job_id)
        if cached is not None:
            return cached
        with self.db.session() as s:
            rec = s.get(JobRecord, job_id)
            return JobState.from_record(rec).to_dict() if rec is not None else None

    def subscribe(self, job_id: str) -> asyncio.Queue | None:
        """A queue receiving (event, job dict) tuples until 'end'; None if not live."""
        q: asyncio.Queue = asyncio.Queue(maxsize=256)
        with self._lock:
            live = self._live.get(job_id)
            if live is None:
                return None
            live.subscribers.append(q)
        return q

    def unsubscribe(self, job_id: str, q: asyncio.Queue) -> None:
        """Stop delivering events to `q`."""
        with self._lock:
            live = self._live.get(job_id)
            if live is not None and q in live.subscribers:
                live.subscribers.remove(q)

    def active_ids(self) -> list[str]:
        """Ids of jobs queued or running in this process."""
        return list(self._live)

    def shutdown(self, timeout_s: float = 5.0) -> None:
        """Stop live jobs (they end `interrupted`) and wait briefly for their drivers.

        Every job's own flag is set first; an executor that cannot pass the cancel on (its
        workers or scheduler already gone) is logged and the other jobs are still stopped."""
        self._stopping = True
        for job_id in list(self._live):
            try:
                self.cancel(job_id)
            except Exception as exc:  # the job's flag is set: its driver still stops
                log.warning("shutdown: the executor did not take job %s's cancel: %s",
                            job_id, _describe(exc))
        deadline = time.monotonic() + timeout_s
        for th in self._threads:
            th.join(max(0.0, deadline - time.monotonic()))

    # -- internals -------------------------------------------------------------------
    def _set(self, job_id: str, **fields: Any) -> None:
        live = self._live[job_id]
        for key, value in fields.items():
            setattr(live.record, key, value)
        with self.db.session() as s:
            self._write(s, job_id, live.record)
        self._publish(job_id, "progress")

    def _write(self, s: Session, job_id: str, state: JobState) -> None:
        row = s.get(JobRecord, job_id)
        if row is not None:
            state.to_record(row)

    def _publish(self, job_id: str, event: str) -> None:
        loop = self._loop
        live = self._live.get(job_id)
        if live is not None:
            live.seq += 1
        if loop is None or live is None or not live.subscribers:
            return
        payload = live.record.copy(eta_s=_eta(live)).to_dict()
        payload["_seq"] = live.seq
        for q in list(live.subscribers):
            loop.call_soon_threadsafe(_offer, q, (event, payload))

    def event_seq(self, job_id: str) -> int | None:
        """Events published so far for a live job (None once it is over)."""
        live = self._live.get(job_id)
        return None if live is None else live.seq


def _offer(q: asyncio.Queue, item: tuple[str, dict[str, Any]]) -> None:
    """Queue an event; drop the oldest progress event if a slow listener fell behind."""
    if q.full():
        q.get_nowait()
    q.put_nowait(item)


def _eta(live: _Live) -> float | None:
    """Seconds left in the current stage from its rate so far (None until measurable)."""
    rec = live.record
    done, total = rec.done, rec.total
    if rec.status != JobStatus.RUNNING or total <= 0 or done <= live.stage_done0:
        return None
    elapsed = time.monotonic() - live.stage_started
    rate = (done - live.stage_done0) / max(elapsed, 1e-6)
    return round(max(0, total - done) / rate, 2)


def _describe(exc: BaseException) -> str:
    """One line naming the error type and its message."""
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {msg}"[:2000] if msg else type(exc).__name__
