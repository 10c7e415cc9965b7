"""The client's protocol core (`api.client.core`) without a server: its steps driven by hand,
and both clients (sync and asyncio) on the same mock transport, which must see the same
requests and give the same answers, errors and files."""

from __future__ import annotations

import asyncio
import inspect
import json
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from api.client import (
    AsyncPhasecalClient,
    JobCancelled,
    JobFailed,
    PhasecalClient,
    ServiceError,
    core,
)

URL = "http://127.0.0.1:9"
Handler = Callable[[httpx.Request], httpx.Response]


class Body(httpx.SyncByteStream, httpx.AsyncByteStream):
    """A response body in pieces that records whether the client closed it."""

    def __init__(self, pieces: list[bytes]) -> None:
        self.pieces = pieces
        self.closed = False

    def __iter__(self) -> Iterator[bytes]:
        yield from self.pieces

    async def __aiter__(self) -> AsyncIterator[bytes]:
        for piece in self.pieces:
            yield piece

    def close(self) -> None:
        self.closed = True

    async def aclose(self) -> None:
        self.closed = True


class Face:
    """One client kind on a mock transport; `call` runs a method to its answer either way."""

    def __init__(self, kind: str, handler: Handler, **kwargs: Any) -> None:
        cls = PhasecalClient if kind == "sync" else AsyncPhasecalClient
        self.kind = kind
        self.client: Any = cls(URL, transport=httpx.MockTransport(handler), **kwargs)

    def call(self, name: str, *args: Any, **kwargs: Any) -> Any:
        out = getattr(self.client, name)(*args, **kwargs)
        return asyncio.run(out) if inspect.iscoroutine(out) else out

    def events(self, job: str) -> list[tuple[str, dict[str, Any]]]:
        if self.kind == "sync":
            return list(self.client.events(job))

        async def collect() -> list[tuple[str, dict[str, Any]]]:
            return [e async for e in self.client.events(job)]

        return asyncio.run(collect())


@pytest.fixture(params=["sync", "async"])
def kind(request: pytest.FixtureRequest) -> str:
    return request.param


def sse(*events: tuple[str, dict[str, Any]], keepalive: bool = True) -> list[bytes]:
    out = [b": keepalive\n\n"] if keepalive else []
    for name, data in events:
        out.append(f"event: {name}\ndata: {json.dumps(data)}\n\n".encode())
    return out


def job(status: str, jid: str = "job_1", **extra: Any) -> dict[str, Any]:
    return {"id": jid, "status": status, "error": extra.pop("error", None), **extra}


def test_send_is_plain_steps_retried_with_one_idempotency_key() -> None:
    steps = core.send("POST", "/sessions", {"json": {"name": "x"}}, retries=2)
    first = core.advance(steps)
    assert isinstance(first, core.Send) and first.method == "POST"
    key = first.options["headers"]["Idempotency-Key"]
    assert core.advance(steps, error=httpx.ConnectError("reset")) == core.Sleep(0.2)
    second = core.advance(steps)
    assert isinstance(second, core.Send) and second.options["headers"]["Idempotency-Key"] == key
    busy = httpx.Response(503, json={"status": 503, "detail": "busy"})
    assert core.advance(steps, busy) == core.Close(busy)
    assert core.advance(steps) == core.Sleep(0.4)
    third = core.advance(steps)
    assert isinstance(third, core.Send) and third.options["headers"]["Idempotency-Key"] == key
    done = core.advance(steps, httpx.Response(201, json={"id": "ses_1"}))
    assert isinstance(done, core.Done) and done.value.json() == {"id": "ses_1"}


def test_a_failed_answer_is_read_then_raised_with_its_problem() -> None:
    steps = core.send("GET", "/sessions/x", {}, retries=0, stream=True)
    assert isinstance(core.advance(steps), core.Send)
    missing = httpx.Response(404, json={"type": "https://phasecal.dev/problems/not-found",
                                        "status": 404, "detail": "no such session"})
    assert core.advance(steps, missing) == core.Close(missing, read=True)
    with pytest.raises(ServiceError) as err:
        core.advance(steps)
    assert err.value.status == 404 and err.value.type.endswith("/not-found")


def test_both_clients_retry_posts_with_the_same_key(kind: str) -> None:
    seen: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request.headers["Idempotency-Key"])
        if len(seen) == 1:
            raise httpx.ConnectError("connection reset")
        if len(seen) == 2:
            return httpx.Response(503, json={"status": 503, "detail": "busy"})
        return httpx.Response(201, json={"id": "ses_1"})

    face = Face(kind, handler, retries=2)
    assert face.call("create_session", "x") == {"id": "ses_1"}
    assert len(seen) == 3 and len(set(seen)) == 1
    seen.clear()
    face.client.retries = 0
    with pytest.raises(httpx.ConnectError):
        face.call("create_session", "x")
    face.call("close")


def test_both_clients_send_the_same_requests() -> None:
    logs: dict[str, list[tuple[str, str, bytes]]] = {}
    for kind in ("sync", "async"):
        log = logs[kind] = []

        def handler(request: httpx.Request, log: list = log) -> httpx.Response:
            log.append((request.method, str(request.url), request.read()))
            return httpx.Response(200, json={"pixels": [[1.0, 2.0]]})

        face = Face(kind, handler)
        face.call("project", "cal/1", [(1, 2, 3)])
        face.call("list_jobs", status="running", limit=5)
        face.call("get", "/health", verbose=1)
        face.call("undistort_points", "cal_2", [[3, 4]], pinhole=[1, 1, 0, 0])
    assert logs["sync"] == logs["async"]
    assert logs["sync"][0][:2] == ("POST", f"{URL}/calibrations/cal%2F1/project")
    assert json.loads(logs["sync"][0][2]) == {"points": [[1.0, 2.0, 3.0]]}


def test_downloads_are_streamed_into_place_and_closed(kind: str, tmp_path: Path) -> None:
    bodies: list[Body] = []

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/export"):
            assert request.url.params["pinhole"] == "1,2,3"
            body = Body([b"%YAML", b":1.0\n"])
            bodies.append(body)
            return httpx.Response(200, stream=body,
                                  headers={"Phasecal-Export-Info": '{"exact": true}'})
        body = Body([b'{"type": ', b'"opencv5"}'])
        bodies.append(body)
        return httpx.Response(200, stream=body)

    face = Face(kind, handler)
    assert face.call("download_file", "cal_1", "model.json", tmp_path / "m.json") == (
        tmp_path / "m.json")
    assert (tmp_path / "m.json").read_text() == '{"type": "opencv5"}'
    assert face.call("export", "cal_1", "remap", tmp_path / "r.yaml", pinhole=[1, 2, 3]) == {
        "exact": True}
    assert (tmp_path / "r.yaml").read_bytes() == b"%YAML:1.0\n"
    assert len(bodies) == 2 and all(b.closed for b in bodies)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "r.yaml"]


def test_a_refused_download_leaves_no_file(kind: str, tmp_path: Path) -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(404, json={"status": 404, "detail": "calibration cal_0 unknown",
                                         "type": "https://phasecal.dev/problems/not-found"})

    face = Face(kind, handler)
    with pytest.raises(ServiceError, match="cal_0 unknown") as err:
        face.call("export", "cal_0", "ros", tmp_path / "x.yaml")
    assert err.value.status == 404 and not list(tmp_path.iterdir())


def test_uploads_are_opened_afresh_for_each_try(kind: str, tmp_path: Path) -> None:
    maps = tmp_path / "maps.npz"
    maps.write_bytes(b"NPZ" * 1000)
    bodies: list[bytes] = []

    def handler(request: httpx.Request) -> httpx.Response:
        bodies.append(request.read())
        if len(bodies) == 1:
            return httpx.Response(503, json={"status": 503, "detail": "busy"})
        return httpx.Response(201, json={"id": "pose_1", "status": "ready"})

    face = Face(kind, handler, retries=1)
    assert face.call("import_maps", "ses_1", maps)["id"] == "pose_1"
    assert len(bodies) == 2 and all(b'filename="maps.npz"' in b and b"NPZ" * 1000 in b
                                    for b in bodies)


def test_wait_follows_the_events_to_the_end_and_raises_the_job_problem(kind: str) -> None:
    bodies: list[Body] = []
    progress = job("running", done=1, total=2)

    def handler(request: httpx.Request) -> httpx.Response:
        assert request.url.path == "/jobs/job_1/events"
        body = Body(sse(("progress", progress),
                        ("end", job("failed", error="options.xp: 'cupy' not importable"))))
        bodies.append(body)
        return httpx.Response(200, stream=body, headers={"Content-Type": "text/event-stream"})

    face = Face(kind, handler)
    seen: list[dict[str, Any]] = []
    with pytest.raises(JobFailed) as err:
        face.call("wait", {"id": "job_1"}, on_progress=seen.append)
    assert not isinstance(err.value, JobCancelled) and err.value.job_status == "failed"
    assert err.value.problem["instance"] == "/jobs/job_1" and "cupy" in err.value.detail
    assert seen == [progress]
    assert face.call("wait", "job_1", check=False)["status"] == "failed"
    assert face.events("job_1") == [("keepalive", {}), ("progress", progress),
                                    ("end", job("failed", error="options.xp: 'cupy' "
                                                                "not importable"))]
    assert len(bodies) == 3 and all(b.closed for b in bodies)


def test_wait_rejoins_a_dropped_stream_after_looking_at_the_job(kind: str) -> None:
    paths: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        paths.append(request.url.path)
        if request.url.path.endswith("/events"):
            return httpx.Response(200, stream=Body(sse()))  # ends without `end`
        state = "running" if paths.count("/jobs/job_1") == 1 else "cancelled"
        return httpx.Response(200, json=job(state))

    face = Face(kind, handler)
    with pytest.raises(JobCancelled):
        face.call("wait", "job_1")
    assert paths == ["/jobs/job_1/events", "/jobs/job_1"] * 2


def test_wait_polls_the_job_while_the_server_has_no_stream_free(kind: str, monkeypatch) -> None:
    monkeypatch.setattr(core, "STREAMS_BUSY_S", 0.01)
    paths: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        paths.append(request.url.path)
        if request.url.path.endswith("/events"):
            return httpx.Response(429, headers={"Retry-After": "2"},
                                  json={"status": 429, "detail": "too many streams"})
        state = "running" if paths.count("/jobs/job_1") == 1 else "succeeded"
        return httpx.Response(200, json=job(state))

    assert Face(kind, handler).call("wait", "job_1")["status"] == "succeeded"
    assert paths == ["/jobs/job_1/events", "/jobs/job_1"] * 2


def test_wait_times_out(kind: str) -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events"):
            return httpx.Response(200, stream=Body(sse(("progress", job("running")))))
        return httpx.Response(200, json=job("running"))

    with pytest.raises(TimeoutError, match="job_1 still running"):
        Face(kind, handler).call("wait", "job_1", timeout_s=0.3)


def test_ctrl_c_during_a_sync_wait_cancels_the_job_and_closes_the_stream() -> None:
    bodies: list[Body] = []
    posts: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        if request.method == "POST":
            posts.append(request.url.path)
            return httpx.Response(200, json=job("cancelled"))
        body = Body(sse(("progress", job("running"))))
        bodies.append(body)
        return httpx.Response(200, stream=body)

    def interrupt(state: dict[str, Any]) -> None:
        raise KeyboardInterrupt

    face = Face("sync", handler)
    with pytest.raises(KeyboardInterrupt):
        face.call("wait", "job_1", on_progress=interrupt)
    assert posts == ["/jobs/job_1/cancel"] and bodies[0].closed
