"""GET next-pose: computed by the executor's worker (not in the server that paces
captures), cached per pose set, with clear problems when it cannot be planned."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from api.worker import guidance_task
from tests.api.test_api_uploads import PLAN, good_maps


@contextmanager
def _service(data: Path, executor: str) -> Iterator[tuple]:
    """A service with one session of 3 imported poses: (client, services, session id, data)."""
    app = create_app(ServiceConfig(data_dir=data, executor=executor))
    with TestClient(app, raise_server_exceptions=False) as c:
        sess = c.post("/sessions", json={"plan": PLAN.to_dict()}).json()
        for k in range(3):
            r = c.post(f"/sessions/{sess['id']}/poses/import-maps",
                       files={"file": ("m.npz", good_maps(20 + k, size=(160, 120))
                                       .to_npz_bytes())})
            assert r.status_code == 201, r.text
        yield c, app.state.services, sess["id"], data


@pytest.fixture(scope="module", params=["threads", "processes"])
def service(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory):
    with _service(tmp_path_factory.mktemp("guidance") / "data", request.param) as svc:
        yield svc


@pytest.fixture(scope="module")
def in_threads(tmp_path_factory: pytest.TempPathFactory):
    """Threads only: a test may patch the fit in this process."""
    with _service(tmp_path_factory.mktemp("guidance-threads") / "data", "threads") as svc:
        yield svc


def _submissions(monkeypatch: pytest.MonkeyPatch, svc) -> list[str]:
    """Record the names of the callables the service submits to its executor."""
    names: list[str] = []
    submit = svc.executor.submit

    def recording(fn, /, *args, **kwargs):
        names.append(fn.__name__)
        return submit(fn, *args, **kwargs)

    monkeypatch.setattr(svc.executor, "submit", recording)
    return names


def test_next_pose_is_planned_by_the_executor_once(service, monkeypatch) -> None:
    client, svc, sid, _ = service
    names = _submissions(monkeypatch, svc)
    first = client.get(f"/sessions/{sid}/next-pose", params={"model": "opencv5"})
    assert first.status_code == 200, first.text
    assert names == ["guidance_task"]
    body = first.json()
    assert body["session_id"] == sid and body["model"] == "opencv5"
    assert len(body["poses_used"]) == 3 and len(body["screen_pose"]["rvec"]) == 3
    image = client.get(body["image"])
    assert image.headers["content-type"] == "image/png" and image.content[:4] == b"\x89PNG"
    again = client.get(f"/sessions/{sid}/next-pose", params={"model": "opencv5"})
    assert again.json() == body and names == ["guidance_task"]  # served from the cache


def test_a_plan_that_fails_is_a_problem_and_leaves_no_scratch(in_threads, monkeypatch) -> None:
    client, _, sid, data = in_threads

    def fails(*args, **kwargs):
        raise ValueError("the poses are too similar to plan from")

    monkeypatch.setattr(guidance_task, "plan_next_pose", fails)
    before = set((data / "tmp").iterdir())
    r = client.get(f"/sessions/{sid}/next-pose", params={"model": "fisheye"})
    assert r.status_code == 422 and r.headers["content-type"].startswith(
        "application/problem+json")
    assert "too similar" in r.json()["detail"]
    assert set((data / "tmp").iterdir()) == before


def test_fewer_than_three_poses_is_a_conflict(service) -> None:
    client, _, _, _ = service
    sess = client.post("/sessions", json={"plan": PLAN.to_dict()}).json()
    r = client.get(f"/sessions/{sess['id']}/next-pose")
    assert r.status_code == 409 and "3 ready" in r.json()["detail"]


def test_plans_of_different_sessions_are_computed_at_the_same_time(tmp_path, monkeypatch) -> None:
    """Each cached plan has its own lock: a session's plan does not wait for another's (both
    plans here wait for each other inside the fit: one global lock would deadlock them until
    the barrier's timeout)."""
    barrier = threading.Barrier(2, timeout=60)
    plan = guidance_task.plan_next_pose

    def together(*args, **kwargs):
        barrier.wait()
        return plan(*args, **kwargs)

    monkeypatch.setattr(guidance_task, "plan_next_pose", together)
    with _service(tmp_path / "data", "threads") as (client, _svc, sid, _):
        other = client.post("/sessions", json={"plan": PLAN.to_dict()}).json()["id"]
        for k in range(3):
            client.post(f"/sessions/{other}/poses/import-maps",
                        files={"file": ("m.npz", good_maps(30 + k, size=(160, 120))
                                        .to_npz_bytes())}).raise_for_status()
        results: dict[str, int] = {}

        def get(session: str) -> None:
            r = client.get(f"/sessions/{session}/next-pose", params={"model": "opencv5"})
            results[session] = r.status_code

        threads = [threading.Thread(target=get, args=(s,)) for s in (sid, other)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert results == {sid: 200, other: 200} and not barrier.broken
