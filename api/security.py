"""Bearer-token check and request-body limits as pure ASGI middleware (problem+json on refusal)."""

from __future__ import annotations

import hmac
import json
from typing import Any
from urllib.parse import unquote_to_bytes

from api.body_limits import BodyLimits, Refusal, shape_refusal, size_refusal
from api.json_shape import JsonShape
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
    """Refuses request bodies past what their route needs (`api.body_limits`): file uploads
    up to `max_bytes` (PHASECAL_MAX_UPLOAD_BYTES), every other body up to the far smaller
    JSON limit and, as it streams in, past a budget of JSON values, arrays/objects and
    nesting depth, so the app never parses a body whose objects would need many times its
    size in memory. Checked by Content-Length up front and on the bytes as they arrive.
    `max_json_bytes` is PHASECAL_MAX_JSON_BYTES."""

    def __init__(self, app: Any, max_bytes: int, max_json_bytes: int) -> None:
        self.app = app
        self.limits = BodyLimits(max_bytes, max_json_bytes)

    async def __call__(self, scope: Scope, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers", []))
        budget = self.limits.for_request(scope.get("path", ""),
                                                     headers.get(b"content-type"))
        declared = headers.get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > budget.max_bytes):
            size = int(declared) if declared.isdigit() else None
            await _answer(send, size_refusal(budget, size))
            return
        shape = JsonShape() if budget.json else None
        seen = 0  # body bytes received so far
        started = False  # a response went out to the client
        refusal: Refusal | None = None  # why the body was refused while streaming

        async def limited_receive() -> dict[str, Any]:
            nonlocal seen, refusal
            msg = await receive()
            if msg["type"] == "http.request" and refusal is None:
                chunk = msg.get("body", b"")
                seen += len(chunk)
                if seen > budget.max_bytes:
                    refusal = size_refusal(budget)
                elif shape is not None:
                    shape.feed(chunk)
                    refusal = shape_refusal(budget, shape)
                if refusal is not None:
                    raise _Refused
            return msg

        async def tracking_send(msg: dict[str, Any]) -> None:
            nonlocal started
            if refusal is not None:
                # The app caught _Refused while reading the body (FastAPI turns any
                # body-reading error into a 400): answer our refusal instead and drop the
                # app's own response.
                if not started:
                    started = True
                    await _answer(send, refusal)
                return
            if msg["type"] == "http.response.start":
                started = True
            await send(msg)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except _Refused:
            if not started and refusal is not None:
                await _answer(send, refusal)


async def _answer(send: Any, refusal: Refusal) -> None:
    """Send a refusal as problem+json."""
    await send_problem(send, refusal.status, refusal.slug, refusal.detail)


class _Refused(Exception):
    """Raised from receive() when a streamed body passes its route's budget."""
