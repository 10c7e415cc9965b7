"""Bearer-token check and request-size limit as pure ASGI middleware (problem+json on refusal)."""

from __future__ import annotations

import hmac
import json
from typing import Any

from api.problems import MEDIA_TYPE, problem_body

Scope = dict[str, Any]
OPEN_PATHS = ("/health",)


async def send_problem(send: Any, status: int, slug: str, detail: str,
                       extra_headers: list[tuple[bytes, bytes]] | None = None) -> None:
    """Answer an ASGI request with a problem+json document."""
    body = json.dumps(problem_body(status, slug, detail)).encode()
    headers = [(b"content-type", MEDIA_TYPE.encode()), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": status,
                "headers": headers + (extra_headers or [])})
    await send({"type": "http.response.body", "body": body})


def token_matches(token: str | None, authorization: str | None) -> bool:
    """True if the server has no token, or `authorization` is `Bearer <token>`."""
    if not token:
        return True
    return hmac.compare_digest((authorization or "").encode(), f"Bearer {token}".encode())


class TokenMiddleware:
    """Requires `Authorization: Bearer <token>` on every request except /health."""

    def __init__(self, app: Any, token: str) -> None:
        self.app = app
        self.expected = f"Bearer {token}".encode()

    async def __call__(self, scope: Scope, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or scope["path"] in OPEN_PATHS:
            await self.app(scope, receive, send)
            return
        got = dict(scope.get("headers", [])).get(b"authorization", b"")
        if not hmac.compare_digest(got, self.expected):
            await send_problem(send, 401, "unauthorized",
                               "missing or wrong API token: send 'Authorization: Bearer <token>'",
                               [(b"www-authenticate", b"Bearer")])
            return
        await self.app(scope, receive, send)


class BodyLimitMiddleware:
    """Rejects request bodies over `max_bytes` (by Content-Length, and while streaming)."""

    def __init__(self, app: Any, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers", [])).get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > self.max_bytes):
            await send_problem(send, 413, "too-large",
                               f"request body of {declared.decode(errors='replace')} bytes exceeds "
                               f"the limit of {self.max_bytes} bytes (PHASECAL_MAX_UPLOAD_BYTES)")
            return
        seen = 0
        started = False  # a response went out to the client
        exceeded = False  # the body passed the limit while streaming
        too_large = f"request body exceeds the limit of {self.max_bytes} bytes"

        async def limited_receive() -> dict[str, Any]:
            nonlocal seen, exceeded
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > self.max_bytes:
                    exceeded = True
                    raise _TooLarge
            return msg

        async def tracking_send(msg: dict[str, Any]) -> None:
            nonlocal started
            if exceeded:
                # The app caught _TooLarge while parsing (FastAPI turns any form-parsing
                # error into a 400): answer 413 instead and drop the app's own response.
                if not started:
                    started = True
                    await send_problem(send, 413, "too-large", too_large)
                return
            if msg["type"] == "http.response.start":
                started = True
            await send(msg)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except _TooLarge:
            if not started:
                await send_problem(send, 413, "too-large", too_large)


class _TooLarge(Exception):
    """Raised from receive() when a streamed body passes the limit."""
