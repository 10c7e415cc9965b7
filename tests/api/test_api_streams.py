"""Long-lived streams cannot starve the server; `default` on every rig path; a 500 keeps
the connection.

MJPEG clients that take one frame and hang up must leave the thread pool of the sync
routes free; `fps` is bounded; open streams are capped per client address and in all
(429 + Retry-After); a client that stops reading is dropped; an unhandled error answers a
500 problem on a connection that stays usable.
"""

from __future__ import annotations

import asyncio
import json
import socket
import sys
import threading
import time
from collections.abc import AsyncIterator, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import pytest
from fastapi import FastAPI, Request

from api.config import ServiceConfig
from api.inprocess import running_service
from api.routes.preview import MAX_FPS, MIN_FPS
from api.stream_limits import (
    DEFAULT_LIMITS,
    EVENTS,
    PREVIEW,
    GuardedStream,
    StreamLimiter,
    StreamLimits,
    set_stream_limits,
)

ROOMY = StreamLimits(per_client=200, total=200)
PREVIEW_CODE = ("api/routes/preview.py", "api/live_preview.py")


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, FastAPI]]:
    data = tmp_path_factory.mktemp("streams") / "data"
    with running_service(ServiceConfig(data_dir=data, executor="threads")) as (url, app):
        yield url, app


@pytest.fixture
def limits(service: tuple[str, FastAPI]) -> Iterator[None]:
    """Give every test fresh default limiters back afterwards."""
    yield
    _, app = service
    for kind in (PREVIEW, EVENTS):
        set_stream_limits(app, kind, DEFAULT_LIMITS[kind])


def default_rig_id(url: str) -> str:
    rigs = httpx.get(f"{url}/rigs", timeout=30).json()
    return next(r["id"] for r in rigs if r["name"] == "default")


def open_stream(url: str, path: str, source: str = "127.0.0.1",
                timeout_s: float = 60) -> tuple[int, socket.socket]:
    """GET `path` on a raw socket; for a 200 read up to the end of the first JPEG.
    Returns the status and the still open socket (the caller closes it: a hang-up)."""
    parts = urlsplit(url)
    sock = socket.create_connection((parts.hostname, parts.port), timeout=timeout_s,
                                    source_address=(source, 0))
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: {parts.netloc}\r\n\r\n".encode())
    buf = b""
    while b"\r\n\r\n" not in buf:
        got = sock.recv(65536)
        if not got:
            break
        buf += got
    status = int(buf.split(b" ", 2)[1])
    head_end = buf.index(b"\r\n\r\n") + 4
    while status == 200 and b"\xff\xd9" not in buf[head_end:]:  # JPEG end-of-image
        got = sock.recv(65536)
        if not got:
            break
        buf += got
    return status, sock


def take_one_frame(url: str, path: str, source: str = "127.0.0.1") -> int:
    """Open a stream, take its first frame, hang up; the status."""
    status, sock = open_stream(url, path, source)
    sock.close()
    return status


def preview_code_threads() -> list[str]:
    """Names of threads currently running the preview's code (route or grab/encode)."""
    names = {t.ident: t.name for t in threading.enumerate()}
    busy = []
    for ident, frame in sys._current_frames().items():
        f = frame
        while f is not None:
            if f.f_code.co_filename.replace("\\", "/").endswith(PREVIEW_CODE):
                busy.append(names.get(ident, str(ident)))
                break
            f = f.f_back
    return busy


def wait_until(cond, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.05)
    return bool(cond())


def test_clients_that_take_one_frame_and_hang_up_leave_sync_routes_answering(
        service: tuple[str, FastAPI], limits: None) -> None:
    url, app = service
    root = Path(__file__).resolve().parents[2]
    assert all((root / p).is_file() for p in PREVIEW_CODE)  # what preview_code_threads finds
    limiter = set_stream_limits(app, PREVIEW, ROOMY)
    path = f"/rigs/{default_rig_id(url)}/camera/preview?fps={MIN_FPS}"
    n = 80  # twice the server's shared thread pool
    with ThreadPoolExecutor(n) as pool:
        statuses = list(pool.map(lambda _: take_one_frame(url, path), range(n)))
    assert statuses == [200] * n
    t0 = time.monotonic()
    r = httpx.get(f"{url}/sessions", timeout=120)  # a sync route: needs a pool thread
    took = time.monotonic() - t0
    assert r.status_code == 200
    # A sync route answers in milliseconds; with one thread per waiting stream it waited
    # until the 1/fps = 5 s sleeps of the hung-up clients' threads ran out.
    assert took < 2.5, f"GET /sessions took {took:.1f} s after the preview clients left"
    # Between frames nothing runs the preview's code on any thread, and every slot is back.
    assert wait_until(lambda: not preview_code_threads(), 2.0), preview_code_threads()
    assert wait_until(lambda: limiter.active() == 0, 3.0), limiter.active()


@pytest.mark.parametrize("fps", [str(MIN_FPS), "1", str(MAX_FPS)])
def test_allowed_fps_stream(service: tuple[str, FastAPI], limits: None, fps: str) -> None:
    url, _ = service
    r = httpx.get(f"{url}/rigs/{default_rig_id(url)}/camera/preview",
                  params={"fps": fps, "frames": 2},
                  timeout=60)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("multipart/x-mixed-replace")
    assert r.content.count(b"--phasecal-frame\r\n") == 2


@pytest.mark.parametrize("fps", ["0.1", "0.05", "1e-6", "0", "-1", "10.5", "1e9", "nan",
                                 "inf", "-inf", "fast"])
def test_disallowed_fps_is_422(service: tuple[str, FastAPI], limits: None, fps: str) -> None:
    url, _ = service
    with httpx.stream("GET", f"{url}/rigs/{default_rig_id(url)}/camera/preview",
                      params={"fps": fps}, timeout=30) as r:  # an accepted stream never ends
        assert r.status_code == 422, (fps, r.status_code)
        assert r.headers["content-type"] == "application/problem+json"
        assert json.loads(r.read())["errors"][0]["loc"] == ["query", "fps"]


def test_stream_caps_per_client_and_in_total_answer_429(
        service: tuple[str, FastAPI], limits: None) -> None:
    url, app = service
    limiter = set_stream_limits(app, PREVIEW, StreamLimits(per_client=2, total=3,
                                                           retry_after_s=3))
    path = f"/rigs/{default_rig_id(url)}/camera/preview?fps={MIN_FPS}"
    held = [open_stream(url, path)[1] for _ in range(2)]
    try:
        with httpx.stream("GET", url + path, timeout=30) as r:  # a third from this address
            assert r.status_code == 429
            assert r.headers["content-type"] == "application/problem+json"
            assert r.headers["retry-after"] == "3"
            body = json.loads(r.read())
        assert body["type"].endswith("/too-many-streams") and "per client" in body["detail"]
        status, other = open_stream(url, path, source="127.0.0.2")  # another client
        assert status == 200
        held.append(other)
        status, sock = open_stream(url, path, source="127.0.0.3")  # over the total
        sock.close()
        assert status == 429
        assert limiter.active() == 3 and limiter.active("127.0.0.1") == 2
        held.pop(0).close()
        assert wait_until(lambda: limiter.active("127.0.0.1") == 1, 3.0)
        status, sock = open_stream(url, path)
        held.append(sock)
        assert status == 200
    finally:
        for sock in held:
            sock.close()
    assert wait_until(lambda: limiter.active() == 0, 3.0), limiter.active()


def test_event_streams_have_their_own_cap(service: tuple[str, FastAPI], limits: None) -> None:
    url, app = service
    limiter = set_stream_limits(app, EVENTS, StreamLimits(per_client=1, total=5))
    slot = limiter.acquire("127.0.0.1")  # one stream of this client is open
    try:
        r = httpx.get(f"{url}/jobs/job_0123456789abcdef/events", timeout=30)
        assert r.status_code == 429 and r.headers["retry-after"] == "2"
        assert r.json()["type"].endswith("/too-many-streams")
    finally:
        slot.release()
    r = httpx.get(f"{url}/jobs/job_0123456789abcdef/events", timeout=30)
    assert r.status_code == 404  # admitted: the job does not exist
    assert limiter.active() == 0


RIG_BODIES = {
    ("PUT", "/rigs/{rig_id}/camera/settings"): {"exposure_s": 0.01},
    ("PUT", "/rigs/{rig_id}/screen-pose"): {"rvec": [0.1, -0.05, 0.0],
                                           "tvec_mm": [-130.0, -100.0, 320.0]},
}


def test_default_names_the_servers_rig_on_every_rig_path(
        service: tuple[str, FastAPI], limits: None) -> None:
    url, app = service
    routes = [(m.upper(), path) for path, ops in app.openapi()["paths"].items()
              if path.startswith("/rigs/{rig_id}") for m in sorted(ops)]
    assert len(routes) >= 6, routes  # rig, settings (GET/PUT), screen pose, both previews
    with httpx.Client(base_url=url, timeout=60) as c:
        for method, path in routes:
            r = c.request(method, path.replace("{rig_id}", "default"),
                          params={"frames": 1} if path.endswith("/preview") else None,
                          json=RIG_BODIES.get((method, path)))
            assert r.status_code == 200, (method, path, r.status_code, r.text[:300])
        assert c.get("/rigs/default").json()["id"] == default_rig_id(url)
        assert c.get("/rigs/defaults/camera/preview.jpg").status_code == 404


def test_unhandled_error_answers_500_problem_and_keeps_the_connection(
        service: tuple[str, FastAPI], limits: None) -> None:
    url, app = service

    async def boom() -> None:
        raise RuntimeError("a test-only failure")

    async def peer(request: Request) -> dict[str, int]:
        return {"port": request.client.port if request.client else -1}

    app.add_api_route("/test-only/boom", boom, methods=["GET"])
    app.add_api_route("/test-only/peer", peer, methods=["GET"])
    with httpx.Client(base_url=url, timeout=30) as c:
        before = c.get("/test-only/peer").json()["port"]
        r = c.get("/test-only/boom")
        assert r.status_code == 500
        assert r.headers["content-type"] == "application/problem+json"
        assert r.json()["type"].endswith("/internal-error")
        assert "RuntimeError" in r.json()["detail"]
        assert r.headers.get("connection", "").lower() != "close"
        after = c.get("/test-only/peer")
        assert after.status_code == 200
        assert after.json()["port"] == before  # the same keep-alive connection


def test_a_client_that_stops_reading_is_dropped_and_releases_its_slot() -> None:
    limiter = StreamLimiter(PREVIEW, StreamLimits(per_client=1, total=1, send_timeout_s=0.2))
    closed = []

    async def endless() -> AsyncIterator[bytes]:
        try:
            while True:
                yield b"x" * 1000
                await asyncio.sleep(0)
        finally:
            closed.append(True)

    async def scenario() -> tuple[float, list[str]]:
        sent: list[str] = []
        stuck = asyncio.Event()

        async def send(message: dict) -> None:
            sent.append(message["type"])
            if len(sent) > 3:  # the client's buffers are full: the send never completes
                await stuck.wait()

        async def receive() -> dict:
            await stuck.wait()  # connected, never hangs up
            return {"type": "http.disconnect"}

        resp = GuardedStream(endless(), limiter.acquire("10.0.0.1"),
                             media_type="application/octet-stream")
        t0 = time.monotonic()
        await asyncio.wait_for(resp({"type": "http"}, receive, send), 30)
        return time.monotonic() - t0, [resp.ended_by, *sent]

    took, (ended_by, *sent) = asyncio.run(scenario())
    assert ended_by == "stalled" and took < 10
    assert sent[0] == "http.response.start" and len(sent) == 4
    assert closed == [True] and limiter.active() == 0


def test_a_hang_up_between_frames_ends_the_stream_at_once() -> None:
    limiter = StreamLimiter(PREVIEW, StreamLimits(per_client=1, total=1))
    closed = []

    async def slow() -> AsyncIterator[bytes]:
        try:
            while True:
                yield b"frame"
                await asyncio.sleep(3600)  # a very slow stream
        finally:
            closed.append(True)

    async def scenario() -> float:
        gone = asyncio.Event()

        async def send(message: dict) -> None:
            if message.get("body") == b"frame":
                gone.set()  # the client takes one frame and hangs up

        async def receive() -> dict:
            await gone.wait()
            return {"type": "http.disconnect"}

        resp = GuardedStream(slow(), limiter.acquire("10.0.0.1"), media_type="image/jpeg")
        t0 = time.monotonic()
        await asyncio.wait_for(resp({"type": "http"}, receive, send), 30)
        assert resp.ended_by == "disconnect"
        return time.monotonic() - t0

    assert asyncio.run(scenario()) < 10
    assert closed == [True] and limiter.active() == 0


def test_stream_limits_are_validated() -> None:
    for bad in ({"per_client": 0}, {"per_client": 5, "total": 4}, {"send_timeout_s": 0},
                {"send_timeout_s": float("nan")}, {"retry_after_s": 0}):
        with pytest.raises(ValueError, match="stream limits"):
            StreamLimits(**bad)

