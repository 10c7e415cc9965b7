"""The synchronous phasecal client: a method per resource, typed answers, problem-details
errors, SSE job waiting, streamed uploads/downloads, idempotent retries. What it does is
written once in `api.client.core` and `api.client.ops`; here are only the blocking I/O of
each step and what a blocking caller does differently (Ctrl-C while waiting)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import httpx

from api.client import core, ops
from api.client import types as t
from api.client.errors import ServiceError
from api.client.methods import Operations

T = TypeVar("T")


class PhasecalClient(Operations):
    """Calls the REST API, blocking. Every POST carries an Idempotency-Key; requests are
    retried (same key) on transport errors and 502/503/504, up to `retries` times with
    backoff."""

    def __init__(self, base_url: str, token: str | None = None, timeout_s: float = 60.0,
                 retries: int = 2, transport: httpx.BaseTransport | None = None) -> None:
        self.http = httpx.Client(**core.pool_options(base_url, token, timeout_s),
                                 transport=transport)
        self.retries = retries

    def close(self) -> None:
        """Close the connection pool."""
        self.http.close()

    def __enter__(self) -> PhasecalClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def run(self, op: ops.Op[T]) -> T:
        """Run an operation description and return its answer."""
        return self._perform(core.perform(op, retries=self.retries))

    def events(self, job: str | t.Job) -> Iterator[tuple[str, dict[str, Any]]]:
        """The job's server-sent events (`progress`..., `end`; keepalives included)."""
        stream = self._perform(core.open_events(job, retries=self.retries,
                                                timeout=self.http.timeout))
        try:
            while (event := self._perform(core.next_event(stream))) is not None:
                yield event
        finally:
            stream.response.close()

    def wait(self, job: str | t.Job | dict[str, Any], timeout_s: float = 600.0,
             check: bool = True, on_progress: Callable[[t.Job], None] | None = None) -> t.Job:
        """Follow the job's SSE stream to its end; its final state.

        `check`: raise `JobFailed` (`JobCancelled`) with the problem details unless it
        succeeded. Interrupted (Ctrl-C) while waiting, the job is cancelled on the server.
        Reconnects if the stream drops; `TimeoutError` after `timeout_s`.
        """
        try:
            final = self._perform(core.follow_job(job, timeout_s, on_progress,
                                                  retries=self.retries, timeout=self.http.timeout))
        except KeyboardInterrupt:
            with contextlib.suppress(ServiceError, httpx.HTTPError):
                self.cancel_job(ops.job_id(job))
            raise
        return core.job_outcome(final, check)

    # -- I/O --------------------------------------------------------------------------------
    def _perform(self, steps: core.Steps[T]) -> T:
        """Run a `core` generator to its result, doing each step it yields; an exception of a
        step goes back into the generator, which handles it or lets it through."""
        step = core.advance(steps)
        while not isinstance(step, core.Done):
            try:
                reply = self._do(step)
            except BaseException as exc:  # Ctrl-C too: the generator closes what it opened
                step = core.advance(steps, error=exc)
            else:
                step = core.advance(steps, reply)
        return step.value

    def _do(self, step: core.Step) -> Any:
        """One step with the blocking httpx pool."""
        match step:
            case core.Send(method, path, options, stream):
                return self.http.send(self.http.build_request(method, path, **options),
                                      stream=stream)
            case core.Sleep(seconds):
                time.sleep(seconds)
            case core.Close(response, read):
                if read:
                    response.read()
                response.close()
            case core.Iterate(response, None):
                return response.iter_lines()
            case core.Iterate(response, size):
                return response.iter_bytes(size)
            case core.Next(items):
                return next(items, None)
        return None
