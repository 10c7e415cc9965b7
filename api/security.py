"""Bearer-token check and request-size limit as pure ASGI middleware (problem+json on refusal)."""

from __future__ import annotations

import hmac
import json
from typing import Any
from urllib.parse import unquote_to_bytes

from api.problems import MEDIA_TYPE, problem_body

Scope = dict[str, Any]
OPEN_PATHS = ("/health", "/")
OPEN_PREFIXES = ("/ui/",)  # the web page's static files: they hold no data
TOKEN_COOKIE = b"phasecal_token"


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


def _cookie(headers: dict[bytes, bytes], name: bytes) -> bytes:
    """One cookie's value from the Cookie header (b"" if absent)."""
    for part in headers.get(b"cookie", b"").split(b";"):
        key, _, value = part.strip().partition(b"=")
        if key == name:
            return value
    return b""


class TokenMiddleware:
    """Requires `Authorization: Bearer <token>` on every request except /health and the web
    page's static files. GET/HEAD may carry the token in the `phasecal_token` cookie instead
    (set by the page, SameSite=Strict): images, reports and SSE streams that a browser loads
    by URL cannot send a header. Anything that changes state needs the header."""

    def __init__(self, app: Any, token: str) -> None:
        self.app = app
        self.expected = f"Bearer {token}".encode()
        self.token = token.encode()

    async def __call__(self, scope: Scope, receive: Any, send: Any) -> None:
        path = scope.get("path", "")
        if scope["type"] != "http" or path in OPEN_PATHS or path.startswith(OPEN_PREFIXES):
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers", []))
        got = headers.get(b"authorization", b"")
        ok = hmac.compare_digest(got, self.expected)
        if not ok and scope.get("method") in ("GET", "HEAD"):
            ok = hmac.compare_digest(unquote_to_bytes(_cookie(headers, TOKEN_COOKIE)), self.token)
        if not ok:
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
