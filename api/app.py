"""The FastAPI application: routes, problem+json errors, security, idempotency, lifecycle."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from api.config import ServiceConfig
from api.idempotency import IdempotencyMiddleware
from api.problems import UnhandledErrorMiddleware, install_handlers
from api.routes import (
    auto,
    batch,
    calibrations,
    deletion,
    exports,
    guidance,
    handeye,
    intrinsics,
    jobs,
    observations,
    pose_frames,
    preview,
    reports,
    rig_calibrations,
    rigs,
    sessions,
    target_rig,
)
from api.security import BodyLimitMiddleware, TokenMiddleware, token_matches
from api.services import Services
from api.storage import NoSpaceMiddleware
from api.timing import ServerTimingMiddleware
from api.version import phasecal_version

WEB_DIR = Path(__file__).parent / "web"  # the page at `/`: plain HTML/JS/CSS, no build step
DESCRIPTION = """Camera calibration with an active phase-shift target.

Flow: create a session (rig + plan), capture or import poses (jobs), calibrate chosen
poses with a model (a job), then download the model, exports and residual plot, or
project/unproject points. Every long operation answers `202 Accepted` with a job
(`Location: /jobs/<id>`): poll it or follow `/jobs/<id>/events` (SSE). Errors are
RFC 9457 `application/problem+json`. POSTs accept an `Idempotency-Key` header so that
a rig script can retry safely.
"""


def create_app(config: ServiceConfig | None = None) -> FastAPI:
    """Build the app for `config` (default: from PHASECAL_* environment variables)."""
    cfg = config or ServiceConfig.from_env()
    cfg.check_security()
    services = Services.build(cfg)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        services.jobs.bind_loop(asyncio.get_running_loop())
        try:
            yield
        finally:  # (Services.close logs a failing step and goes on: it never raises)
            await asyncio.to_thread(services.close)

    app = FastAPI(title="phasecal", version=phasecal_version(), description=DESCRIPTION,
                  lifespan=lifespan)
    app.state.services = services
    install_handlers(app)
    for module in (
        rigs,
        preview,
        sessions,
        pose_frames,
        guidance,
        intrinsics,
        calibrations,
        handeye,
        auto,
        observations,
        rig_calibrations,
        target_rig,
        reports,
        exports,
        batch,
        jobs,
        deletion,
    ):
        app.include_router(module.router)

    @app.get("/", include_in_schema=False)
    def page() -> FileResponse:
        """The operator's web page (static; it talks to this API with the same token)."""
        return FileResponse(WEB_DIR / "index.html", media_type="text/html")

    app.mount("/ui", StaticFiles(directory=WEB_DIR), name="ui")

    @app.get("/health", tags=["service"])
    async def health(request: Request) -> dict[str, Any]:
        """Liveness: status (`ok`, or `degraded` with the reasons, e.g. low on space) and the
        number of active jobs; the data directory and its free space only for clients that
        sent the API token (or when the server has none). Async: it never blocks, and a sync
        endpoint would queue probes behind the thread pool and the GIL."""
        space = services.space.report()
        body: dict[str, Any] = {"status": "ok", "active_jobs": len(services.jobs.active_ids())}
        if space.degraded:
            body.update(status="degraded", reasons=[space.degraded])
        if token_matches(cfg.token, request.headers.get("authorization")):
            body["data_dir"] = str(services.store.root)
            body["storage"] = space.to_dict()
        return body

    app.add_middleware(IdempotencyMiddleware, db_getter=lambda: services.db)
    app.add_middleware(NoSpaceMiddleware, space=services.space)  # also idempotency's writes
    app.add_middleware(BodyLimitMiddleware, max_bytes=cfg.max_upload_bytes,
                       max_json_bytes=cfg.max_json_bytes)
    if cfg.token:
        app.add_middleware(TokenMiddleware, token=cfg.token)
    # around every middleware above: an error none of them answered is a 500 problem that
    # keeps the connection (a full disk was answered 507 further in)
    app.add_middleware(UnhandledErrorMiddleware)
    app.add_middleware(ServerTimingMiddleware)  # outermost: times everything above
    return app


def app_from_env() -> FastAPI:
    """Factory for `uvicorn --factory api.app:app_from_env` (config from PHASECAL_* env)."""
    return create_app(ServiceConfig.from_env())
