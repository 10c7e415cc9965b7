"""Every response carries the server's own time (`Server-Timing: app;dur=<ms>`)."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig


def test_server_timing_header_on_answers_and_problems(tmp_path: Path) -> None:
    app = create_app(ServiceConfig(data_dir=tmp_path / "d", executor="threads", token="t"))
    with TestClient(app) as c:
        for r in (c.get("/health"), c.get("/sessions"),  # the second: 401 from the middleware
                  c.get("/sessions", headers={"Authorization": "Bearer t"})):
            name, _, dur = r.headers["server-timing"].partition(";dur=")
            assert name == "app" and 0 <= float(dur) < 60_000, r.headers
