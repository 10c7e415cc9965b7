"""What both clients do, written once without doing any I/O (the sans-I/O pattern).

Each function here is a generator of steps: it yields the I/O it needs (`Send` a request,
`Sleep`, `Close` a response, `Iterate` a streamed body's lines or chunks and take the
`Next` one) and is sent back what the step gave, or has the step's
exception thrown in. Everything else is decided here: the Idempotency-Key of a POST, which
failures are retried and the backoff, the problem details of a 4xx/5xx answer, where a
download is written, how a job's event stream is followed to its end. `PhasecalClient`
(`api.client.sync`) and `AsyncPhasecalClient` (`api.client.aio`) only perform the steps,
with `httpx.Client` or `httpx.AsyncClient`, so the two cannot drift apart.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
import uuid
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import httpx

from api.client import ops
from api.client import types as t
from api.client.errors import ServiceError, job_error, raise_for_problem

T = TypeVar("T")
RETRY_STATUS = (502, 503, 504)
BACKOFF_S = 0.2  # before retry k (0-based): BACKOFF_S * 2**k
SSE_READ_TIMEOUT_S = 45.0  # the server sends a keepalive every 15 s
JOB_POLL_S = 0.2  # between a dropped event stream and the next one
TOO_MANY_STREAMS = 429  # the server's answer while its event streams are all taken
STREAMS_BUSY_S = 2.0  # then the job is polled this often (the server's Retry-After)
CHUNK = 1 << 20


@dataclass(frozen=True)
class Send:
    """Build the request on the client's pool (`build_request(method, path, **options)`) and
    send it; gives the response (its body unread with `stream`)."""

    method: str
    path: str
    options: dict[str, Any]
    stream: bool = False


@dataclass(frozen=True)
class Sleep:
    """Wait `seconds` (a retry's backoff, the pause before reconnecting)."""

    seconds: float


@dataclass(frozen=True)
class Close:
    """Close a response (a streamed one gives its connection back); with `read`, read its
    whole body first (the problem document of a failed streamed request)."""

    response: httpx.Response
    read: bool = False


@dataclass(frozen=True)
class Iterate:
    """Start iterating a streamed body: its text lines, or chunks of up to `chunk_size`
    bytes; gives the iterator for `Next`."""

    response: httpx.Response
    chunk_size: int | None = None


@dataclass(frozen=True)
class Next:
    """The next item of an iterator from `Iterate`; None at its end."""

    items: Any


@dataclass(frozen=True)
class Done:
    """What `advance` gives when the generator has finished: its result."""

    value: Any


Step = Send | Sleep | Close | Iterate | Next
Steps = Generator[Step, Any, T]


def advance(steps: Steps[Any], reply: Any = None, error: BaseException | None = None
            ) -> Step | Done:
    """The generator's next step after the last one gave `reply` (or raised `error`, which
    the generator handles or lets through to the caller); `Done` once it returned."""
    try:
        return steps.send(reply) if error is None else steps.throw(error)
    except StopIteration as done:
        return Done(done.value)


def pool_options(base_url: str, token: str | None, timeout_s: float) -> dict[str, Any]:
    """The settings of both clients' httpx pools: base URL, bearer token, timeout."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return {"base_url": base_url, "headers": headers, "timeout": timeout_s}


def send(method: str, path: str, options: dict[str, Any], *, retries: int,
         stream: bool = False, upload: ops.Opener | None = None) -> Steps[httpx.Response]:
    """The response to a request: a POST carries an Idempotency-Key, kept through `retries`
    more tries on transport errors and 502/503/504 (backoff 0.2 s, 0.4 s, ...); an upload is
    opened afresh for each try. A 4xx/5xx raises `ServiceError` with the problem details."""
    options = dict(options)
    headers = dict(options.pop("headers", None) or {})
    if method == "POST":
        headers.setdefault("Idempotency-Key", uuid.uuid4().hex)
    for attempt in range(retries + 1):
        handles: list[Any] = []
        try:
            if upload is not None:
                options["files"], handles = upload()
            try:
                r = yield Send(method, path, {**options, "headers": headers}, stream)
            except httpx.TransportError:
                if attempt == retries:
                    raise
            else:
                if r.status_code not in RETRY_STATUS or attempt == retries:
                    if r.status_code >= 400:
                        yield Close(r, read=True)
                        raise_for_problem(r)
                    return r
                yield Close(r)
        finally:
            for fh in handles:
                fh.close()
        yield Sleep(BACKOFF_S * 2**attempt)
    raise AssertionError("unreachable")


def perform(op: ops.Op[T], *, retries: int) -> Steps[T]:
    """One operation: its request (as `send`), its body saved to `op.save_to` if it names a
    file, then its answer."""
    r = yield from send(op.method, op.path, op.request_options(), retries=retries,
                        stream=op.stream or op.save_to is not None, upload=op.upload)
    if op.save_to is not None:
        yield from closing(r, save_body(r, op.save_to))
    return op.answer(r)


def closing(response: httpx.Response, steps: Steps[T]) -> Steps[T]:
    """Run `steps` on a streamed response, then close it, whatever happened."""
    try:
        result = yield from steps
    except GeneratorExit:
        raise  # abandoned by its client: no step can run now; the response stays with its pool
    except BaseException:
        yield Close(response)
        raise
    yield Close(response)
    return result


def save_body(r: httpx.Response, dest: Path) -> Steps[None]:
    """Stream a body into `dest`: written under a temporary name in its folder and renamed,
    so `dest` is never a partial file (the temporary one is removed if anything fails)."""
    fd, tmp = tempfile.mkstemp(prefix=dest.name + ".", suffix=".part", dir=dest.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            chunks = yield Iterate(r, CHUNK)
            while (chunk := (yield Next(chunks))) is not None:
                fh.write(chunk)
        os.replace(tmp, dest)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# -- server-sent events ---------------------------------------------------------------------------
class SSEDecoder:
    """Feed SSE text lines; complete events come back as (event, data), keepalives as
    ("keepalive", {}) so a waiting client can check its deadline."""

    def __init__(self) -> None:
        self.event, self.data = "message", []  # type: tuple[str, list[str]]

    def feed(self, line: str) -> tuple[str, dict[str, Any]] | None:
        """One line without its newline -> an event when it completes one."""
        if line.startswith(":"):
            return ("keepalive", {})
        if line.startswith("event:"):
            self.event = line[6:].strip()
        elif line.startswith("data:"):
            self.data.append(line[5:].lstrip())
        elif line == "" and self.data:
            out = (self.event, json.loads("\n".join(self.data)))
            self.event, self.data = "message", []
            return out
        return None


@dataclass
class EventStream:
    """A job's open event stream: the response (the caller closes it), its lines, the decoder."""

    response: httpx.Response
    lines: Any
    decoder: SSEDecoder = field(default_factory=SSEDecoder)


def open_events(job: str | t.Job, *, retries: int, timeout: httpx.Timeout
                ) -> Steps[EventStream]:
    """Open `GET /jobs/{id}/events`; the read timeout outlasts the server's keepalives,
    the other timeouts are the client's (`timeout`)."""
    sse_timeout = httpx.Timeout(timeout.connect, read=SSE_READ_TIMEOUT_S)
    r = yield from send("GET", ops.job_events_path(job), {"timeout": sse_timeout},
                        retries=retries, stream=True)
    return EventStream(r, (yield Iterate(r)))


def next_event(stream: EventStream) -> Steps[tuple[str, dict[str, Any]] | None]:
    """The stream's next event (keepalives included); None when the server ended it."""
    while (line := (yield Next(stream.lines))) is not None:
        event = stream.decoder.feed(line)
        if event is not None:
            return event
    return None


def follow_job(job: str | t.Job | dict[str, Any], timeout_s: float,
               on_progress: Callable[[t.Job], None] | None, *, retries: int,
               timeout: httpx.Timeout) -> Steps[t.Job]:
    """The job's final state, from its event stream (`on_progress` gets every progress
    event); a dropped stream is re-joined after looking at the job, and while the server has
    too many streams open (429) the job is polled until one is free; `TimeoutError` once
    `timeout_s` has passed."""
    jid = ops.job_id(job)
    deadline = time.monotonic() + timeout_s
    while True:
        busy = False
        try:
            stream = yield from open_events(jid, retries=retries, timeout=timeout)
            final = yield from closing(stream.response, until_end(stream, deadline, on_progress))
        except httpx.TransportError:
            final = None  # stream dropped: look at the job, then reconnect
        except ServiceError as exc:
            if exc.status != TOO_MANY_STREAMS:
                raise
            final, busy = None, True
        if final is not None:
            return final
        state = yield from perform(ops.get_job(jid), retries=retries)
        if state["status"] in t.TERMINAL:
            return state
        if time.monotonic() > deadline:
            raise TimeoutError(f"job {jid} still {state['status']} at the deadline")
        yield Sleep(STREAMS_BUSY_S if busy else JOB_POLL_S)


def until_end(stream: EventStream, deadline: float,
              on_progress: Callable[[t.Job], None] | None) -> Steps[t.Job | None]:
    """Read a job's events up to its `end` (the final state) or, None, to the deadline or the
    end of the stream."""
    while (event := (yield from next_event(stream))) is not None:
        kind, data = event
        if kind == "end":
            return data  # type: ignore[return-value]
        if kind == "progress" and on_progress is not None:
            on_progress(data)  # type: ignore[arg-type]
        if time.monotonic() > deadline:
            return None
    return None


def job_outcome(final: t.Job, check: bool) -> t.Job:
    """The final state of a waited-for job; with `check`, `JobFailed` (`JobCancelled`) unless
    it succeeded."""
    if check and final["status"] != "succeeded":
        raise job_error(final)
    return final
