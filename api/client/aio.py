"""The asyncio phasecal client (httpx.AsyncClient): the same methods as `PhasecalClient`,
awaitable; job waits follow the SSE stream and cancel the server job if the task is
cancelled. What it does is written once in `api.client.core` and `api.client.ops`; here are
only the awaited I/O of each step and what an asyncio caller does differently."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from typing import Any, TypeVar

import httpx

from api.client import core, ops
from api.client import types as t
from api.client.errors import ServiceError
from api.client.methods import Operations

T = TypeVar("T")


class AsyncPhasecalClient(Operations):
    """Calls the REST API from asyncio code (every method awaitable). Every POST carries an
    Idempotency-Key; requests are retried (same key) on transport errors and 502/503/504, up
    to `retries` times with backoff."""

    def __init__(self, base_url: str, token: str | None = None, timeout_s: float = 60.0,
                 retries: int = 2, transport: httpx.AsyncBaseTransport | None = None) -> None:
        self.http = httpx.AsyncClient(**core.pool_options(base_url, token, timeout_s),
                                      transport=transport)
        self.retries = retries

    async def close(self) -> None:
        """Close the connection pool."""
        await self.http.aclose()

    async def __aenter__(self) -> AsyncPhasecalClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def run(self, op: ops.Op[T]) -> T:
        """Run an operation description and return its answer."""
        return await self._perform(core.perform(op, retries=self.retries))

    async def events(self, job: str | t.Job) -> AsyncIterator[tuple[str, dict[str, Any]]]:
        """The job's server-sent events (`progress`..., `end`; keepalives included)."""
        stream = await self._perform(core.open_events(job, retries=self.retries,
                                                      timeout=self.http.timeout))
        try:
            while (event := await self._perform(core.next_event(stream))) is not None:
                yield event
        finally:
            await stream.response.aclose()

    async def wait(self, job: str | t.Job | dict[str, Any], timeout_s: float = 600.0,
                   check: bool = True, on_progress: Callable[[t.Job], None] | None = None
                   ) -> t.Job:
        """Follow the job's SSE stream to its end; its final state.

        `check`: raise `JobFailed` (`JobCancelled`) with the problem details unless it
        succeeded. If the waiting task is cancelled, the job is cancelled on the server.
        Reconnects if the stream drops; `TimeoutError` after `timeout_s`.
        """
        try:
            final = await self._perform(core.follow_job(
                job, timeout_s, on_progress, retries=self.retries, timeout=self.http.timeout))
        except asyncio.CancelledError:
            with contextlib.suppress(ServiceError, httpx.HTTPError):
                await asyncio.shield(self.cancel_job(ops.job_id(job)))
            raise
        return core.job_outcome(final, check)

    # -- I/O --------------------------------------------------------------------------------
    async def _perform(self, steps: core.Steps[T]) -> T:
        """Run a `core` generator to its result, awaiting each step it yields; an exception of
        a step goes back into the generator, which handles it or lets it through."""
        step = core.advance(steps)
        while not isinstance(step, core.Done):
            try:
                reply = await self._do(step)
            except BaseException as exc:  # cancellation too: the generator closes what it opened
                step = core.advance(steps, error=exc)
            else:
                step = core.advance(steps, reply)
        return step.value

    async def _do(self, step: core.Step) -> Any:
        """One step with the asyncio httpx pool."""
        match step:
            case core.Send(method, path, options, stream):
                return await self.http.send(self.http.build_request(method, path, **options),
                                            stream=stream)
            case core.Sleep(seconds):
                await asyncio.sleep(seconds)
            case core.Close(response, read):
                if read:
                    await response.aread()
                await response.aclose()
            case core.Iterate(response, None):
                return response.aiter_lines()
            case core.Iterate(response, size):
                return response.aiter_bytes(size)
            case core.Next(items):
                return await anext(items, None)
        return None
