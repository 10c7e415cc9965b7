"""RFC 9457 problem+json errors: one exception type, handlers for every error path."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from acquisition.errors import AcquisitionError, DeviceSettingsError
from calibration import ModelError
from calibration.shared.maps import MapsError
from calibration.shared.plan import PlanError

PROBLEM_TYPE_BASE = "https://phasecal.dev/problems/"
MEDIA_TYPE = "application/problem+json"

log = logging.getLogger("phasecal.api")
MAX_LISTED_ERRORS = 20  # a validation problem lists this many errors (and counts the rest)

_TITLES = {
    400: "Bad request",
    401: "Unauthorized",
    403: "Forbidden",
    404: "Not found",
    405: "Method not allowed",
    406: "Not acceptable",
    409: "Conflict",
    413: "Content too large",
    415: "Unsupported media type",
    422: "Unprocessable content",
    429: "Too many requests",
    500: "Internal server error",
    503: "Service unavailable",
    507: "Insufficient storage",
}


class Problem(Exception):
    """An error answered as problem+json: status, short type slug and a specific detail
    (plus response headers such as Retry-After, and extra members of the document)."""

    def __init__(self, status: int, slug: str, detail: str,
                 headers: dict[str, str] | None = None, **extra: Any) -> None:
        super().__init__(detail)
        self.status = status
        self.slug = slug
        self.detail = detail
        self.headers = headers
        self.extra = extra


def problem_body(status: int, slug: str, detail: str, instance: str | None = None,
                 **extra: Any) -> dict[str, Any]:
    """The problem+json document."""
    body: dict[str, Any] = {
        "type": PROBLEM_TYPE_BASE + slug,
        "title": _TITLES.get(status, "Error"),
        "status": status,
        "detail": detail,
    }
    if instance:
        body["instance"] = instance
    body.update(extra)
    return body


def problem_response(status: int, slug: str, detail: str, instance: str | None = None,
                     headers: dict[str, str] | None = None, **extra: Any) -> JSONResponse:
    """A JSONResponse with the problem+json media type."""
    return JSONResponse(
        problem_body(status, slug, detail, instance, **extra),
        status_code=status,
        media_type=MEDIA_TYPE,
        headers=headers,
    )


def _allowed_methods(request: Request) -> list[str]:
    """Every method some route accepts for this path (FastAPI has one route per method)."""
    methods: set[str] = set()
    scope = dict(request.scope, method="GET")
    for route in request.app.router.routes:
        match, _ = route.matches(scope)
        if match != Match.NONE:
            methods |= set(getattr(route, "methods", None) or ())
    return sorted(methods)


def install_handlers(app: FastAPI) -> None:
    """Route every error (ours, HTTP, validation, domain, unexpected) to problem+json."""
    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem) -> JSONResponse:
        return problem_response(exc.status, exc.slug, exc.detail, request.url.path,
                                headers=exc.headers, **exc.extra)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        slug = {404: "not-found", 405: "method-not-allowed"}.get(exc.status_code, "http-error")
        detail = str(exc.detail) if exc.detail else _TITLES.get(exc.status_code, "Error")
        if exc.status_code == 404 and exc.detail == "Not Found":
            detail = f"no route {request.method} {request.url.path}"
        headers = dict(getattr(exc, "headers", None) or {})
        if exc.status_code == 405:
            headers["Allow"] = ", ".join(_allowed_methods(request))
            detail = (f"{request.method} is not allowed on {request.url.path}; "
                      f"use {headers['Allow']}")
        return problem_response(exc.status_code, slug, detail, request.url.path,
                                headers=headers or None)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        found = exc.errors()
        errors = [
            {"loc": [str(p) for p in e.get("loc", ())], "msg": str(e.get("msg", ""))}
            for e in found[:MAX_LISTED_ERRORS]
        ]
        first = errors[0] if errors else {"loc": [], "msg": "invalid request"}
        detail = f"{'.'.join(first['loc'])}: {first['msg']}"
        extra = {"errors_total": len(found)} if len(found) > MAX_LISTED_ERRORS else {}
        return problem_response(422, "validation-error", detail, request.url.path, errors=errors,
                                **extra)

    @app.exception_handler(PlanError)
    async def _plan(request: Request, exc: PlanError) -> JSONResponse:
        return problem_response(422, "invalid-plan", str(exc), request.url.path)

    @app.exception_handler(MapsError)
    async def _maps(request: Request, exc: MapsError) -> JSONResponse:
        return problem_response(422, "invalid-maps", str(exc), request.url.path)

    @app.exception_handler(ModelError)
    async def _model(request: Request, exc: ModelError) -> JSONResponse:
        return problem_response(422, "invalid-model", str(exc), request.url.path)

    @app.exception_handler(DeviceSettingsError)
    async def _settings(request: Request, exc: DeviceSettingsError) -> JSONResponse:
        return problem_response(422, "invalid-device-setting", str(exc), request.url.path)

    @app.exception_handler(AcquisitionError)
    async def _acq(request: Request, exc: AcquisitionError) -> JSONResponse:
        return problem_response(503, "device-error", str(exc), request.url.path)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        # Reached only for errors raised outside UnhandledErrorMiddleware (which the app
        # adds around its other middleware); Starlette then re-raises and the server closes
        # the connection.
        return internal_error(request.method, request.url.path, exc)


def internal_error(method: str, path: str, exc: BaseException) -> JSONResponse:
    """Log an unexpected error with its traceback; the 500 problem answering it."""
    log.error("unhandled error on %s %s", method, path, exc_info=exc)
    return problem_response(500, "internal-error",
                            f"internal error ({type(exc).__name__}); see the server log", path)


class StartTracking:
    """An ASGI `send` that remembers whether the response has started: before that, an error
    can still be answered with a problem; after it, only the connection can be cut."""

    def __init__(self, send: Any) -> None:
        self.send = send
        self.started = False

    async def __call__(self, message: dict[str, Any]) -> None:
        if message["type"] == "http.response.start":
            self.started = True
        await self.send(message)


class UnhandledErrorMiddleware:
    """Answers an error no handler took with a 500 problem and keeps the connection usable.

    Starlette's outermost error middleware answers such an error too, but then re-raises
    it, and the server closes the keep-alive connection, so the client's next request on
    it fails. Here the error ends with the answer. An error after the response has started
    is re-raised: that response is cut short and the connection cannot be reused anyway.
    """

    def __init__(self, app: Any) -> None:
        self.app = app

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        tracked = StartTracking(send)
        try:
            await self.app(scope, receive, tracked)
        except Exception as exc:
            if tracked.started:
                raise
            response = internal_error(scope.get("method", ""), scope.get("path", ""), exc)
            await response(scope, receive, send)
