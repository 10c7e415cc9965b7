"""Long-lived streams (MJPEG preview, SSE job events) that cannot starve the server.

A stream is an async generator on the event loop: waiting between items holds no thread.
It runs inside a `GuardedStream` response that

- ends as soon as the client hangs up (a task listens for `http.disconnect` while the
  generator sleeps, so a client that leaves between two frames is let go at once),
- drops a client whose connection has stopped taking data for `send_timeout_s` (its
  socket buffers are full; waiting longer would pin the stream for as long as the client
  keeps the connection open),
- gives back its `StreamSlot` however it ends.

Slots come from a `StreamLimiter` per kind of stream: at most `per_client` concurrent
streams per client address and `total` in all; beyond that a request is answered 429
problem+json with `Retry-After`. Clients behind one proxy share one address.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import Counter
from collections.abc import AsyncIterator, Mapping
from dataclasses import dataclass
from typing import Any

import anyio
from fastapi import FastAPI, Request
from starlette.responses import StreamingResponse

from api.problems import Problem

log = logging.getLogger("phasecal.api")

PREVIEW = "preview"  # MJPEG camera previews
EVENTS = "events"  # SSE job events


@dataclass(frozen=True)
class StreamLimits:
    """Caps of one kind of stream and how long a send may stall before the client is dropped."""

    per_client: int = 4
    total: int = 32
    send_timeout_s: float = 1.0
    retry_after_s: int = 2

    def __post_init__(self) -> None:
        if self.per_client < 1 or self.total < self.per_client:
            raise ValueError(f"stream limits: need 1 <= per_client <= total, got "
                             f"per_client={self.per_client}, total={self.total}")
        if not (math.isfinite(self.send_timeout_s) and self.send_timeout_s > 0):
            raise ValueError(f"stream limits: send_timeout_s must be > 0, "
                             f"got {self.send_timeout_s}")
        if self.retry_after_s < 1:
            raise ValueError(f"stream limits: retry_after_s must be >= 1, "
                             f"got {self.retry_after_s}")


#: A browser shows one preview per rig; a script follows one event stream per job it waits on.
DEFAULT_LIMITS: Mapping[str, StreamLimits] = {
    PREVIEW: StreamLimits(per_client=4, total=32),
    EVENTS: StreamLimits(per_client=32, total=256),
}


class StreamSlot:
    """One admitted stream; `release` (idempotent) gives the place back to its limiter."""

    def __init__(self, limiter: StreamLimiter, client: str) -> None:
        self.limiter = limiter
        self.client = client
        self.released = False

    def release(self) -> None:
        """Give the slot back (a second call does nothing)."""
        if not self.released:
            self.released = True
            self.limiter.give_back(self.client)


class StreamLimiter:
    """Counts the open streams of one kind, per client address and in total."""

    def __init__(self, kind: str, limits: StreamLimits) -> None:
        self.kind = kind
        self.limits = limits
        self._lock = threading.Lock()
        self._per_client: Counter[str] = Counter()
        self._total = 0

    def acquire(self, client: str) -> StreamSlot:
        """A slot for a new stream of `client`, or a 429 problem with Retry-After."""
        lim = self.limits
        with self._lock:
            if self._per_client[client] >= lim.per_client:
                why = (f"this client already has {self._per_client[client]} open {self.kind} "
                       f"streams (at most {lim.per_client} per client)")
            elif self._total >= lim.total:
                why = f"the server has {self._total} open {self.kind} streams (at most {lim.total})"
            else:
                self._per_client[client] += 1
                self._total += 1
                return StreamSlot(self, client)
        raise Problem(429, "too-many-streams", f"{why}; close one or retry later",
                      headers={"Retry-After": str(lim.retry_after_s)})

    def give_back(self, client: str) -> None:
        """One stream of `client` ended (called by `StreamSlot.release`)."""
        with self._lock:
            self._per_client[client] -= 1
            if self._per_client[client] <= 0:
                del self._per_client[client]
            self._total -= 1

    def active(self, client: str | None = None) -> int:
        """Open streams of `client`, or of everyone."""
        with self._lock:
            return self._total if client is None else self._per_client.get(client, 0)


def client_address(request: Request) -> str:
    """The peer address streams are counted by (the proxy's, behind a reverse proxy)."""
    return request.client.host if request.client is not None else "unknown"


def stream_limiter(app: FastAPI, kind: str) -> StreamLimiter:
    """The app's limiter for `kind` (`PREVIEW`, `EVENTS`), made with `DEFAULT_LIMITS` on
    first use; kept on `app.state` so that every app (and test server) counts its own."""
    limiters: dict[str, StreamLimiter] | None = getattr(app.state, "stream_limiters", None)
    if limiters is None:
        limiters = {}
        app.state.stream_limiters = limiters
    if kind not in limiters:
        limiters[kind] = StreamLimiter(kind, DEFAULT_LIMITS[kind])
    return limiters[kind]


def set_stream_limits(app: FastAPI, kind: str, limits: StreamLimits) -> StreamLimiter:
    """Replace the app's limits for `kind` (a fresh limiter: streams already open are not
    counted by it)."""
    stream_limiter(app, kind)
    limiter = StreamLimiter(kind, limits)
    app.state.stream_limiters[kind] = limiter
    return limiter


class GuardedStream(StreamingResponse):
    """A streaming response that ends on hang-up or a stalled send and releases its slot.

    Owns the request's `receive` while it streams: the generator must not read it (e.g.
    via `Request.is_disconnected`).
    """

    def __init__(self, content: AsyncIterator[bytes | str], slot: StreamSlot,
                 media_type: str, headers: Mapping[str, str] | None = None) -> None:
        super().__init__(content, media_type=media_type, headers=headers)
        self.chunks = content
        self.slot = slot
        self.send_timeout_s = slot.limiter.limits.send_timeout_s
        self.ended_by = ""  # "complete", "disconnect", "stalled" once it ran

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        try:
            async with anyio.create_task_group() as tg:
                tg.start_soon(self._watch_disconnect, receive, tg.cancel_scope)
                try:
                    await self._stream(send)
                finally:
                    tg.cancel_scope.cancel()
        finally:
            try:
                close = getattr(self.chunks, "aclose", None)  # runs the generator's `finally`
                if close is not None:
                    with anyio.CancelScope(shield=True):
                        await close()
            finally:
                self.slot.release()

    async def _watch_disconnect(self, receive: Any, scope: anyio.CancelScope) -> None:
        while (await receive())["type"] != "http.disconnect":
            pass
        self.ended_by = self.ended_by or "disconnect"
        scope.cancel()

    async def _send(self, send: Any, message: dict[str, Any]) -> bool:
        """Send within `send_timeout_s`; False if the client stopped taking data."""
        with anyio.move_on_after(self.send_timeout_s) as timer:
            await send(message)
        if timer.cancelled_caught:
            self.ended_by = self.ended_by or "stalled"
            log.info("%s stream of %s: the client took no data for %.1f s; dropped",
                     self.slot.limiter.kind, self.slot.client, self.send_timeout_s)
            return False
        return True

    async def _stream(self, send: Any) -> None:
        start = {"type": "http.response.start", "status": self.status_code,
                 "headers": self.raw_headers}
        if not await self._send(send, start):
            return
        async for chunk in self.chunks:
            body = chunk if isinstance(chunk, bytes) else chunk.encode(self.charset)
            if not await self._send(send, {"type": "http.response.body", "body": body,
                                           "more_body": True}):
                return  # the server closes the connection: the response is incomplete
        if await self._send(send, {"type": "http.response.body", "body": b"",
                                   "more_body": False}):
            self.ended_by = self.ended_by or "complete"
