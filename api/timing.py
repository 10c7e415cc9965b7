"""Server-side request time as a `Server-Timing: app;dur=<ms>` response header.

Measured from the moment the app receives the request to the start of its response, so
clients (and `benchmarks/api.py`) can tell server time from queueing on the network, the
event loop's accept backlog and their own CPU.
"""

from __future__ import annotations

import time
from typing import Any


class ServerTimingMiddleware:
    """Pure ASGI middleware adding `Server-Timing: app;dur=<ms>` to every HTTP response."""

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()

        async def timed_send(msg: dict[str, Any]) -> None:
            if msg["type"] == "http.response.start":
                ms = (time.perf_counter() - t0) * 1e3
                msg = dict(msg, headers=[*msg.get("headers", []),
                                         (b"server-timing", f"app;dur={ms:.3f}".encode())])
            await send(msg)

        await self.app(scope, receive, timed_send)
