"""Unit tests of the service's building blocks: executor, store, jobs, middleware, errors."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig, is_loopback
from api.db import Database
from api.jobs import Job, JobKind, JobManager
from api.problems import Problem
from api.store import DataStore, check_id, new_id
from api.worker.executor import InProcessExecutor, make_executor
from calibration.shared.progress import Cancelled, TaskContext

PLAN = {
    "format": "phasecal.plan/1",
    "screen": {"width_px": 64, "height_px": 48, "pitch_mm": [0.5, 0.5]},
    "frames": [
        {"kind": "flat", "level": 1.0},
        {"kind": "flat", "level": 0.0},
        *[{"kind": "cosine", "axis": a, "period_px": 80.0, "step": s, "steps": 4}
          for a in "xy" for s in range(4)],
    ],
}


def _count_task(ctx: TaskContext, n: int, delay: float) -> dict:
    for i in range(n):
        ctx.check_cancelled()
        time.sleep(delay)
        ctx.progress(i + 1, n, "count")
    return {"n": n}


def test_executor_runs_tasks_with_progress_and_cancel() -> None:
    ex = InProcessExecutor(max_workers=2)
    seen: list[tuple[int, int, str]] = []
    fut = ex.run_task(_count_task, 3, 0.0, job_id="job_a", on_progress=lambda *a: seen.append(a))
    assert fut.result(timeout=10) == {"n": 3}
    assert seen[-1] == (3, 3, "count")
    slow = ex.run_task(_count_task, 1000, 0.01, job_id="job_b")
    time.sleep(0.05)
    assert ex.cancel("job_b") is True
    with pytest.raises(Cancelled):
        slow.result(timeout=10)
    assert ex.cancel("job_b") is False  # forgotten once done
    assert ex.submit(sum, [1, 2, 3]).result() == 6
    ex.shutdown()


def test_make_executor_rejects_bad_address(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("PHASECAL_DASK", raising=False)
    assert isinstance(make_executor(None), InProcessExecutor)
    with pytest.raises(ValueError, match="tcp://host:port"):
        make_executor("http://example")


def test_store_ids_and_paths(tmp_path: Path) -> None:
    store = DataStore(tmp_path)
    sid = new_id("ses")
    assert check_id(sid, "ses", "session") == sid
    for bad in ("../etc", "ses_../../x", "ses_0123", sid.upper(), "pose_" + sid[4:]):
        with pytest.raises(Problem) as err:
            check_id(bad, "ses", "session")
        assert err.value.status == 404
    folder = store.dir_for(sid)
    assert folder.parent == tmp_path.resolve() / "sessions"
    for name in ("../x", ".hidden", "a/b", ""):
        with pytest.raises(Problem):
            store.file(sid, name)
    target = store.file(sid, "plan.json")
    store.write_bytes(target, b"{}")
    assert target.read_bytes() == b"{}"
    assert not list(folder.glob("*.tmp"))


@dataclass(kw_only=True)
class FnJob(Job):
    """A job made of test callables (body, success and failure hooks)."""

    kind_: str = "decode"
    body: Callable[[TaskContext], dict[str, Any]] = lambda ctx: {}
    ok: Callable[[Any, dict[str, Any]], None] = lambda s, r: None
    fail: Callable[[Any, str, str], None] = lambda s, st, e: None

    def __post_init__(self) -> None:
        self.kind = JobKind(self.kind_)  # type: ignore[misc]  # one class for every kind

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        return self.body(ctx)

    def succeeded(self, s: Any, result: dict[str, Any]) -> None:
        self.ok(s, result)

    def ended(self, s: Any, status: str, error: str) -> None:
        self.fail(s, status, error)


def test_job_manager_states_progress_cancel_recover(tmp_path: Path) -> None:
    db = Database(tmp_path / "db.sqlite")
    jm = JobManager(db, InProcessExecutor(max_workers=2))
    outcomes: dict[str, str] = {}

    def body(ctx: TaskContext) -> dict:
        return jm.executor.run_task(_count_task, 5, 0.01, job_id=ctx.job_id,
                                    on_progress=ctx.progress).result()

    fn = FnJob(body=body, ok=lambda s, r: outcomes.__setitem__("ok", r["n"]),
               fail=lambda s, st, e: outcomes.__setitem__("fail", st))
    with db.session() as s:
        job = jm.create(s, fn)
    jm.start(job.id, fn)
    _wait(lambda: jm.get(job.id)["status"] == "succeeded")
    got = jm.get(job.id)
    assert (got["done"], got["total"], outcomes) == (5, 5, {"ok": 5})

    slow_job = FnJob(fail=lambda s, st, e: outcomes.__setitem__("fail", st))
    with db.session() as s:
        slow = jm.create(s, slow_job)
    started = threading.Event()

    def slow_body(ctx: TaskContext) -> dict:
        started.set()
        return jm.executor.run_task(_count_task, 10_000, 0.005, job_id=ctx.job_id).result()

    slow_job.body = slow_body
    jm.start(slow.id, slow_job)
    started.wait(5)
    assert jm.cancel(slow.id)
    _wait(lambda: jm.get(slow.id)["status"] == "cancelled")
    assert outcomes["fail"] == "cancelled"

    with db.session() as s:
        stale = jm.create(s, FnJob(kind_="capture"))
    restarted = JobManager(db, jm.executor)
    assert restarted.recover("server restarted") == [stale.id]
    rec = restarted.get(stale.id)
    assert (rec["status"], rec["error"]) == ("interrupted", "server restarted")
    jm.executor.shutdown()


def test_job_is_reported_finished_only_after_its_outcome_is_committed(tmp_path: Path) -> None:
    """GET /jobs is served from memory: it must not say 'succeeded' while the transaction
    holding the outcome (job row, and the hook's resource such as a pose becoming 'ready')
    is still uncommitted, or a client reads a stale resource."""
    from contextlib import contextmanager

    from api.db import JobRecord

    class SlowCommitDatabase(Database):
        @contextmanager
        def session(self):
            with super().session() as s:
                yield s
                time.sleep(0.05)  # commit happens after this, on leaving super().session()

    db = SlowCommitDatabase(tmp_path / "db.sqlite")
    jm = JobManager(db, InProcessExecutor(max_workers=1))
    fn = FnJob(body=lambda ctx: {"n": 1})
    with db.session() as s:
        job = jm.create(s, fn)
    jm.start(job.id, fn)
    while jm.get(job.id)["status"] != "succeeded":
        time.sleep(0.001)
    with db.session() as s:
        assert s.get(JobRecord, job.id).status == "succeeded"
    jm.executor.shutdown()


def _wait(cond, timeout: float = 20.0) -> None:
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            raise AssertionError("condition not reached in time")
        time.sleep(0.01)


def test_security_config() -> None:
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0")
    with pytest.raises(ValueError, match="requires an API token"):
        ServiceConfig(host="0.0.0.0").check_security()
    ServiceConfig(host="0.0.0.0", token="s3cret").check_security()


@pytest.fixture
def client(tmp_path: Path):
    cfg = ServiceConfig(data_dir=tmp_path / "data", token="tok", max_upload_bytes=4096)
    with TestClient(create_app(cfg)) as c:
        c.headers["Authorization"] = "Bearer tok"
        yield c


def test_token_required(client: TestClient) -> None:
    assert client.get("/health").status_code == 200
    r = client.get("/sessions", headers={"Authorization": "Bearer wrong"})
    assert r.status_code == 401
    assert r.headers["content-type"] == "application/problem+json"
    assert "token" in r.json()["detail"]


def test_problem_json_for_bad_input(client: TestClient) -> None:
    cases = [
        client.get("/sessions/ses_0123456789abcdef"),
        client.get("/sessions/..%2F..%2Fetc"),
        client.get("/jobs/job_nothere"),
        client.get("/no/such/route"),
        client.post("/sessions", content=b"not json", headers={"content-type": "text/plain"}),
        client.post("/sessions", json={"plan": {"format": "nope"}}),
        client.post("/sessions", json={"bogus": 1}),
        client.post("/sessions", content=b"x" * 5000, headers={"content-type": "application/json"}),
    ]
    for r in cases:
        assert 400 <= r.status_code < 500, (r.request.url, r.status_code, r.text)
        body = r.json()
        assert r.headers["content-type"] == "application/problem+json"
        assert body["status"] == r.status_code and body["detail"]
    assert cases[5].json()["detail"].startswith("plan: format")
    assert cases[7].status_code == 413


def test_chunked_upload_over_the_limit_is_413(client: TestClient) -> None:
    """No Content-Length (chunked): the limit trips while the multipart body streams."""
    sid = client.post("/sessions", json={"name": "chunked", "plan": PLAN}).json()["id"]
    head = (b'--B\r\nContent-Disposition: form-data; name="files"; filename="f.npy"\r\n'
            b"Content-Type: application/octet-stream\r\n\r\n")

    def body():
        yield head
        for _ in range(10):
            yield b"x" * 1000
        yield b"\r\n--B--\r\n"

    r = client.post(f"/sessions/{sid}/poses/import", content=body(),
                    headers={"content-type": "multipart/form-data; boundary=B"})
    assert "content-length" not in r.request.headers
    assert r.status_code == 413, r.text
    assert r.headers["content-type"] == "application/problem+json"
    assert "4096 bytes" in r.json()["detail"]
    assert client.get(f"/sessions/{sid}/poses").json() == []


def test_idempotent_post_replays(client: TestClient) -> None:
    body = {"name": "idem", "plan": PLAN}
    h = {"Idempotency-Key": "k-1"}
    a = client.post("/sessions", json=body, headers=h)
    b = client.post("/sessions", json=body, headers=h)
    assert a.status_code == b.status_code == 201
    assert a.json()["id"] == b.json()["id"]
    assert b.headers.get("idempotent-replayed") == "true"
    assert len(client.get("/sessions").json()) == 1
    c = client.post("/sessions", json={"name": "other", "plan": PLAN}, headers=h)
    assert c.status_code == 422 and "different request" in c.json()["detail"]
    d = client.post("/sessions", json={"name": "other", "plan": PLAN})
    assert d.json()["id"] != a.json()["id"]


def test_idempotent_replay_of_a_body_larger_than_the_memory_spool(tmp_path: Path) -> None:
    """Bodies over 1 MiB are spooled to a temporary file for hashing, then replayed in chunks."""
    from api.idempotency import REPLAY_CHUNK, SPOOL_IN_MEMORY

    cfg = ServiceConfig(data_dir=tmp_path / "data", max_upload_bytes=16 << 20)
    payload = json.dumps({"name": "big", "plan": PLAN}).encode()
    body = payload + b" " * (2 * SPOOL_IN_MEMORY + REPLAY_CHUNK // 3)  # JSON allows whitespace
    h = {"Idempotency-Key": "big-1", "content-type": "application/json"}
    with TestClient(create_app(cfg)) as c:
        a = c.post("/sessions", content=body, headers=h)
        b = c.post("/sessions", content=body, headers=h)
        assert a.status_code == b.status_code == 201, a.text
        assert b.headers.get("idempotent-replayed") == "true"
        assert a.json()["id"] == b.json()["id"]
        other = c.post("/sessions", content=body[:-1] + b"\n", headers=h)
        assert other.status_code == 422 and "different request" in other.json()["detail"]
        assert len(c.get("/sessions").json()) == 1


def test_serve_refuses_public_bind_without_token(capsys: pytest.CaptureFixture[str],
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    from api.cli import main

    monkeypatch.delenv("PHASECAL_TOKEN", raising=False)
    assert main(["serve", "--host", "0.0.0.0", "--port", "1"]) == 1
    assert "requires an API token" in capsys.readouterr().err


def test_process_executor_progress_and_cancel() -> None:
    ex = make_executor("processes")
    try:
        seen: list[tuple[int, int, str]] = []
        fut = ex.run_task(_count_task, 3, 0.0, job_id="p1", on_progress=lambda *a: seen.append(a))
        assert fut.result(timeout=60) == {"n": 3}
        _wait(lambda: (3, 3, "count") in seen)
        slow = ex.run_task(_count_task, 100_000, 0.01, job_id="p2")
        _wait(lambda: slow.running())
        time.sleep(0.2)
        assert ex.cancel("p2")
        with pytest.raises(Cancelled):
            slow.result(timeout=60)
    finally:
        ex.shutdown()


def test_default_rig_is_addressable_by_name(client: TestClient) -> None:
    """docs/api.md: `default` names the rig the server was started with, in every rig path."""
    listed = client.get("/rigs").json()
    default = next(r for r in listed if r["name"] == "default")
    got = client.get("/rigs/default")
    assert got.status_code == 200 and got.json() == default
    assert client.get("/rigs/default/camera/settings").json() == \
        client.get(f"/rigs/{default['id']}/camera/settings").json()
    assert client.get("/rigs/nondefault").status_code == 404
