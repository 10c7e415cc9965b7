"""Jobs: status with progress and ETA, listing with filters, cancel, live SSE events.

The event stream runs on the event loop and ends when the client hangs up or stops
reading; open streams are capped per client and in all (`api.stream_limits`).
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response, StreamingResponse
from sqlalchemy import func, select

from api.db import JobRecord
from api.jobs.model import TERMINAL_JOB_STATES, JobState
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, TOO_MANY_STREAMS
from api.schemas import MAX_OFFSET, Job, JobKind, JobPage, JobStatus
from api.services import Services, get_services
from api.store import check_id
from api.stream_limits import EVENTS, GuardedStream, client_address, stream_limiter

router = APIRouter(tags=["jobs"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
KEEPALIVE_S = 15.0


def _job(svc: Services, job_id: str) -> dict[str, Any]:
    check_id(job_id, "job", "job")
    job = svc.jobs.get(job_id)
    if job is None:
        raise Problem(404, "not-found", f"job {job_id!r} does not exist")
    return job


@router.get("/jobs", response_model=JobPage)
def list_jobs(svc: Svc, status: JobStatus | None = None, kind: JobKind | None = None,
              session_id: str | None = None,
              limit: Annotated[int, Query(ge=1, le=500)] = 50,
              offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0) -> dict[str, Any]:
    """Jobs newest first, filtered by status, kind and session; paginated by limit/offset."""
    conds = []
    if status is not None:
        conds.append(JobRecord.status == status)
    if kind is not None:
        conds.append(JobRecord.kind == kind)
    if session_id is not None:
        conds.append(JobRecord.session_id == session_id)
    with svc.db.session() as s:
        total = s.scalar(select(func.count()).select_from(JobRecord).where(*conds)) or 0
        recs = s.scalars(select(JobRecord).where(*conds)
                         .order_by(JobRecord.created_at.desc(), JobRecord.id)
                         .limit(limit).offset(offset)).all()
        items = [svc.jobs.snapshot(r.id) or JobState.from_record(r).to_dict() for r in recs]
    return {"items": items, "total": int(total), "limit": limit, "offset": offset}


@router.get("/jobs/{job_id}", response_model=Job)
async def read_job(job_id: str, request: Request) -> dict[str, Any]:
    """One job: status, stage, done/total, ETA (served from memory while it runs)."""
    svc: Services = request.app.state.services
    check_id(job_id, "job", "job")
    cached = svc.jobs.cached(job_id)
    if cached is not None:
        return cached
    return await asyncio.to_thread(_job, svc, job_id)


@router.post("/jobs/{job_id}/cancel", response_model=Job, status_code=202)
def cancel_job(job_id: str, svc: Svc) -> dict[str, Any]:
    """Ask a queued/running job to stop; it ends as `cancelled` (409 if already finished)."""
    job = _job(svc, job_id)
    if job["status"] in TERMINAL_JOB_STATES or not svc.jobs.cancel(job_id):
        raise Problem(409, "conflict", f"job {job_id} is {job['status']}; it cannot be cancelled")
    return svc.jobs.get(job_id) or job


def _sse(event: str, data: dict[str, Any], event_id: int | str | None = None) -> str:
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {event}\ndata: {json.dumps(data)}\n\n"


def _last_event_id(request: Request) -> int:
    """The Last-Event-ID a reconnecting client sent (0 if none or not ours)."""
    raw = request.headers.get("last-event-id", "")
    return int(raw) if raw.isdigit() else 0


@router.get("/jobs/{job_id}/events", response_class=StreamingResponse,
            responses={200: {"content": {"text/event-stream": {}},
                             "description": "progress events until an `end` event"},
                       **TOO_MANY_STREAMS})
async def job_events(job_id: str, request: Request) -> Response:
    """Server-sent events: `progress` on every change, then `end` with the final state.

    Every event has an `id` (the job's event count; `end` for the last). A client that
    reconnects with `Last-Event-ID` gets the current state if it changed since that event,
    then the live events: progress events are snapshots, so nothing is lost by the gap.
    Each client address may follow a few dozen jobs at once (429 with Retry-After beyond).
    """
    svc: Services = request.app.state.services
    check_id(job_id, "job", "job")
    slot = stream_limiter(request.app, EVENTS).acquire(client_address(request))
    try:
        seq0 = svc.jobs.event_seq(job_id) or 0  # read first: `first` is at least this new
        first = await asyncio.to_thread(_job, svc, job_id)
    except BaseException:
        slot.release()
        raise
    seen = _last_event_id(request)

    async def stream() -> AsyncIterator[str]:
        yield "retry: 1000\n\n"
        queue = svc.jobs.subscribe(job_id)
        if queue is None:
            final = await asyncio.to_thread(_job, svc, job_id)
            yield _sse("end", final, "end")
            return
        try:
            if seq0 == 0 or seq0 > seen:
                yield _sse("progress", first, seq0)
            while True:
                try:
                    event, data = await asyncio.wait_for(queue.get(), KEEPALIVE_S)
                except TimeoutError:
                    if svc.jobs.event_seq(job_id) is None:  # ended as we subscribed
                        yield _sse("end", await asyncio.to_thread(_job, svc, job_id), "end")
                        return
                    yield ": keepalive\n\n"
                    continue
                seq = data.get("_seq")
                data = {k: v for k, v in data.items() if k != "_seq"}  # shared by listeners
                if event == "end":
                    final = await asyncio.to_thread(_job, svc, job_id)
                    yield _sse("end", final, "end")
                    return
                if seq is None or seq > seen:
                    yield _sse(event, data, seq)
        finally:
            svc.jobs.unsubscribe(job_id, queue)

    return GuardedStream(stream(), slot, media_type="text/event-stream",
                         headers={"Cache-Control": "no-cache"})
