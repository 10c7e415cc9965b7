"""Pose guidance over REST: next-pose computed by the executor's worker (not in the server
that paces captures), cached per pose set under a key its picture URL carries, with clear
problems when it cannot be planned; starting poses with no pose yet; the variety check."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from api.worker import guidance_task
from calibration.guidance_start import nominal_camera, starting_poses
from hw_mocks.cameras import mild_pinhole
from hw_mocks.scene import ScreenPose
from hw_mocks.synthetic import synthetic_maps
from tests.api.test_api_uploads import PLAN, good_maps

SIZE = (160, 120)  # the default simulated rig's camera, as the imported maps


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
    corners = np.array(body["outline_px"])
    inside = np.all((corners >= 0) & (corners < SIZE))
    assert corners.shape == (4, 2) and inside == body["full_screen_visible"]
    assert (body["screen_visible_fraction"] == 1.0) == body["full_screen_visible"]
    assert body["placement"] and isinstance(body["helps"], bool) and body["advice"]
    assert isinstance(body["model_note"], str)
    assert body["image"].endswith(f"&key={body['key']}")
    image = client.get(body["image"])
    assert image.headers["content-type"] == "image/png" and image.content[:4] == b"\x89PNG"
    assert "immutable" in image.headers["cache-control"]
    current = client.get(f"/sessions/{sid}/next-pose.png", params={"model": "opencv5"})
    assert current.content == image.content and current.headers["cache-control"] == "no-cache"
    again = client.get(f"/sessions/{sid}/next-pose", params={"model": "opencv5"})
    assert again.json() == body and names == ["guidance_task"]
    assert again.headers["cache-control"] == "no-cache"
    stale = client.get(f"/sessions/{sid}/next-pose.png", params={"key": "0" * 16})
    assert stale.status_code == 404 and "next-pose" in stale.json()["detail"]


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
    assert r.status_code == 409 and ">= 3 distinct" in r.json()["detail"]


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


def _import(client: TestClient, sid: str, maps) -> str:
    r = client.post(f"/sessions/{sid}/poses/import-maps",
                    files={"file": ("m.npz", maps.to_npz_bytes())})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def test_starting_poses_need_no_pose_and_know_the_ones_taken(in_threads) -> None:
    client, _, _, _ = in_threads
    sid = client.post("/sessions", json={"plan": PLAN.to_dict()}).json()["id"]
    r = client.get(f"/sessions/{sid}/starting-poses", params={"count": 4})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["camera"]["image_size"] == list(SIZE) and "60 deg" in body["camera"]["assumed"]
    assert len(body["poses"]) == 4 and all(p["captured_by"] is None for p in body["poses"])
    for p in body["poses"]:
        corners = np.array(p["outline_px"])
        assert corners.shape == (4, 2) and np.all((corners >= 0) & (corners < SIZE))
        assert "mm from the camera" in p["placement"] and len(p["screen_pose"]["tvec_mm"]) == 3
    # the simulated camera captures the second suggestion: that item names the pose
    camera = nominal_camera(SIZE)
    second = starting_poses(camera, PLAN.screen, 4)[1]
    maps, _ = synthetic_maps(mild_pinhole(*SIZE), ScreenPose(second.rotation,
                                                              second.translation),
                             PLAN.screen, sigma_px=0.05, rng=np.random.default_rng(3))
    maps.meta["plan_digest"] = PLAN.digest()
    pose_id = _import(client, sid, maps)
    after = client.get(f"/sessions/{sid}/starting-poses", params={"count": 4}).json()
    assert [p["captured_by"] for p in after["poses"]] == [None, pose_id, None, None]


def test_guidance_rejects_bad_parameters_by_name(in_threads) -> None:
    client, _, sid, _ = in_threads
    for params, field in (({"count": 0}, "count"), ({"hfov_deg": 170}, "hfov_deg"),
                          ({"hfov_deg": 250, "lens": "fisheye"}, "hfov_deg"),
                          ({"lens": "zoom"}, "lens")):
        r = client.get(f"/sessions/{sid}/starting-poses", params=params)
        assert r.status_code == 422 and field in r.text
    r = client.get(f"/sessions/{sid}/next-pose", params={"min_screen_visible": 0.3})
    assert r.status_code == 422 and "min_screen_visible" in r.text
    assert client.get("/sessions/ses_0000000000000000/starting-poses").status_code == 404
    wide = client.get(f"/sessions/{sid}/starting-poses",
                      params={"lens": "fisheye", "hfov_deg": 170, "count": 2}).json()
    assert wide["camera"]["projection"] == "fisheye" and len(wide["poses"]) == 2


def test_repeated_poses_are_named_and_guidance_says_why_it_waits(in_threads) -> None:
    client, _, _, _ = in_threads
    sid = client.post("/sessions", json={"plan": PLAN.to_dict()}).json()["id"]
    empty = client.get(f"/sessions/{sid}/pose-variety").json()
    assert empty["ready_for_guidance"] is False and empty["duplicates"] == []
    maps = good_maps(40, size=SIZE)
    ids = [_import(client, sid, maps) for _ in range(3)]
    v = client.get(f"/sessions/{sid}/pose-variety")
    assert v.status_code == 200 and v.headers["cache-control"] == "no-cache"
    body = v.json()
    assert body["ready_for_guidance"] is False
    assert not any(body["ready_for_calibration"].values())
    assert [(d["pose_id"], d["repeats"]) for d in body["duplicates"]] == [
        (ids[1], ids[0]), (ids[2], ids[0])]
    assert all(d["similarity"] > 0.9 for d in body["duplicates"])
    r = client.get(f"/sessions/{sid}/next-pose")
    assert r.status_code == 409 and "repeat" in r.json()["detail"]


def test_varied_poses_are_ready(service) -> None:
    client, _, sid, _ = service
    body = client.get(f"/sessions/{sid}/pose-variety").json()
    assert body["ready_for_guidance"] is True and body["duplicates"] == []
    assert body["ready_for_calibration"]["opencv5"] is True


def test_the_guide_command_answers_as_the_routes(tmp_path: Path) -> None:
    from api.cli import main as cli_main

    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps(PLAN.to_dict()))
    paths = []
    for k in range(3):
        paths.append(tmp_path / f"m{k}.npz")
        paths[-1].write_bytes(good_maps(20 + k, size=SIZE).to_npz_bytes())
    out = tmp_path / "guide.json"
    assert cli_main(["guide", "--plan", str(plan), "--maps", *map(str, paths), "--model",
                     "opencv5", "-o", str(out), "--image", str(tmp_path / "n.png")]) == 0
    body = json.loads(out.read_text())
    assert body["pose_variety"]["ready_for_guidance"] and len(body["next_pose"]["outline_px"]) == 4
    assert (tmp_path / "n.png").read_bytes()[:4] == b"\x89PNG"
    assert cli_main(["guide", "--plan", str(plan), "--starting", "3", "--image-size", "160x120",
                     "-o", str(out)]) == 0
    assert [p["captured_by"] for p in json.loads(out.read_text())["starting_poses"]["poses"]
            ] == [None] * 3
    same = [str(paths[0])] * 3
    assert cli_main(["guide", "--plan", str(plan), "--maps", *same]) == 1
    assert cli_main(["guide", "--plan", str(plan), "--starting", "3"]) == 1
