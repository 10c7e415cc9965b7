"""Job manager: every long operation is a job with state, progress, ETA, cancel and events.

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

from sqlalchemy import delete, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from api.db import ACTIVE_JOB_STATES, Database, JobLockRecord, JobRecord
from api.problems import Problem
from api.store import new_id
from calibration.progress import Cancelled, TaskContext
from calibration.worker.executor import Executor

log = logging.getLogger("phasecal.jobs")

PERSIST_INTERVAL_S = 0.5
RECENT_CAPACITY = 2048  # finished jobs answered from memory (status polls after the end)

Hook = Callable[[Session, dict[str, Any]], None]
FailHook = Callable[[Session, str, str], None]


@dataclass
class _Live:
    """In-memory state of a running job."""

    record: dict[str, Any]
    cancel: threading.Event = field(default_factory=threading.Event)
    stage_started: float = field(default_factory=time.monotonic)
    stage_done0: int = 0
    persisted_at: float = 0.0
    subscribers: list[asyncio.Queue] = field(default_factory=list)
    seq: int = 0  # events published so far: the SSE event id (resume with Last-Event-ID)


def job_to_dict(rec: JobRecord) -> dict[str, Any]:
    """A job record as plain data (the API's Job schema, without ETA)."""
    return {
        "id": rec.id,
        "kind": rec.kind,
        "status": rec.status,
        "stage": rec.stage,
        "done": rec.done,
        "total": rec.total,
        "eta_s": None,
        "resource": rec.resource,
        "session_id": rec.session_id,
        "error": rec.error,
        "result": rec.result,
        "created_at": rec.created_at,
        "started_at": rec.started_at,
        "finished_at": rec.finished_at,
    }


class JobManager:
    """Creates, runs, tracks, cancels and recovers jobs; publishes events to SSE listeners."""

    def __init__(self, db: Database, executor: Executor) -> None:
        self.db = db
        self.executor = executor
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
                rec.status = "interrupted"
                rec.error = reason
                rec.finished_at = now
                ids.append(rec.id)
            s.execute(delete(JobLockRecord))
        return ids

    def create(self, s: Session, kind: str, resource: str | None, session_id: str | None,
               total: int = 0, claims: tuple[str, ...] = ()) -> JobRecord:
        """Insert a queued job in the caller's transaction (started later with `start`).

        `claims`: ids of the poses/calibrations the job works on; a resource already
        claimed by an active job is a 409 (enforced by the job_locks primary key).
        """
        rec = JobRecord(id=new_id("job"), kind=kind, status="queued", stage="queued", done=0,
                        total=total, resource=resource, session_id=session_id,
                        created_at=time.time())
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
            self._live[rec.id] = _Live(job_to_dict(rec))
        return rec

    def start(self, job_id: str, body: Callable[[TaskContext], dict[str, Any]],
              on_success: Hook, on_failure: FailHook) -> None:
        """Run `body(ctx)` on a driver thread; hooks update the resource in the same commit."""
        live = self._live[job_id]
        ctx = TaskContext(job_id, lambda d, t, st: self.progress(job_id, d, t, st), live.cancel)
        th = threading.Thread(target=self._drive, args=(job_id, body, ctx, on_success, on_failure),
                              name=f"job-{job_id}", daemon=True)
        self._threads = [t for t in self._threads if t.is_alive()] + [th]
        th.start()

    def _drive(self, job_id: str, body: Callable[[TaskContext], dict[str, Any]],
               ctx: TaskContext, on_success: Hook, on_failure: FailHook) -> None:
        self._set(job_id, status="running", started_at=time.time(), stage="starting")
        try:
            ctx.check_cancelled()
            result = body(ctx)
        except Cancelled:
            self._finish(job_id, *self._stop_reason(), None, on_failure, None)
        except Exception as exc:  # every failure of a job is reported on the job
            if self._live[job_id].cancel.is_set():
                self._finish(job_id, *self._stop_reason(), None, on_failure, None)
            else:
                log.info("job %s failed", job_id, exc_info=True)
                self._finish(job_id, "failed", _describe(exc), None, on_failure, None)
        else:
            self._finish(job_id, "succeeded", None, result, None, on_success)

    def _stop_reason(self) -> tuple[str, str]:
        """(status, reason) of a job stopped by cancel or by the server shutting down."""
        if self._stopping:
            return "interrupted", "interrupted: the server shut down while this job was active"
        return "cancelled", "cancelled on request"

    def _finish(self, job_id: str, status: str, error: str | None, result: dict[str, Any] | None,
                on_failure: FailHook | None, on_success: Hook | None) -> None:
        live = self._live[job_id]
        # The in-memory record (what GET /jobs serves) takes the final state only after the
        # commit: a client seeing "succeeded" must find the resource updated too.
        final = dict(live.record, status=status, error=error, result=result,
                     finished_at=time.time(), stage=status)
        try:
            with self.db.session() as s:
                if on_success is not None:
                    on_success(s, result or {})
                if on_failure is not None:
                    on_failure(s, status, error or "")
                self._write(s, job_id, final)
                s.execute(delete(JobLockRecord).where(JobLockRecord.job_id == job_id))
        except Exception as exc:  # a failing hook must still end the job
            log.exception("finishing job %s failed", job_id)
            final = dict(live.record, status="failed",
                         error=f"could not store the job's outcome: {_describe(exc)}",
                         finished_at=time.time(), stage="failed")
            with self.db.session() as s:
                self._write(s, job_id, final)
                s.execute(delete(JobLockRecord).where(JobLockRecord.job_id == job_id))
        live.record.update(final)
        with self._lock:
            self._recent[job_id] = dict(live.record, eta_s=None)
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
        if stage != rec["stage"]:
            live.stage_started, live.stage_done0 = now, done
        rec.update(done=done, total=total, stage=stage)
        if now - live.persisted_at >= PERSIST_INTERVAL_S:
            live.persisted_at = now
            with self.db.session() as s:
                self._write(s, job_id, rec)
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
        rec = dict(live.record)
        rec["eta_s"] = _eta(live, rec)
        return rec

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
            return job_to_dict(rec) if rec is not None else None

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
        """Stop live jobs (they end `interrupted`) and wait briefly for their drivers."""
        self._stopping = True
        for job_id in list(self._live):
            self.cancel(job_id)
        deadline = time.monotonic() + timeout_s
        for th in self._threads:
            th.join(max(0.0, deadline - time.monotonic()))

    # -- internals -------------------------------------------------------------------
    def _set(self, job_id: str, **fields: Any) -> None:
        live = self._live[job_id]
        live.record.update(fields)
        with self.db.session() as s:
            self._write(s, job_id, live.record)
        self._publish(job_id, "progress")

    def _write(self, s: Session, job_id: str, rec: dict[str, Any], **fields: Any) -> None:
        rec.update(fields)
        row = s.get(JobRecord, job_id)
        if row is None:
            return
        for key in ("status", "stage", "done", "total", "error", "result", "started_at",
                    "finished_at"):
            setattr(row, key, rec[key])

    def _publish(self, job_id: str, event: str) -> None:
        loop = self._loop
        live = self._live.get(job_id)
        if live is not None:
            live.seq += 1
        if loop is None or live is None or not live.subscribers:
            return
        payload = dict(live.record)
        payload["eta_s"] = _eta(live, payload)
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


def _eta(live: _Live, rec: dict[str, Any]) -> float | None:
    """Seconds left in the current stage from its rate so far (None until measurable)."""
    done, total = rec.get("done", 0), rec.get("total", 0)
    if rec.get("status") != "running" or total <= 0 or done <= live.stage_done0:
        return None
    elapsed = time.monotonic() - live.stage_started
    rate = (done - live.stage_done0) / max(elapsed, 1e-6)
    return round(max(0, total - done) / rate, 2)


def _describe(exc: BaseException) -> str:
    """One line naming the error type and its message."""
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {msg}"[:2000] if msg else type(exc).__name__
