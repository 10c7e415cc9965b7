"""Next-pose guidance on a session of two simulated cameras: the suggestion names the
cameras it serves with each camera's predicted worst ray sigma now and after, counts the
views the pair shares, and the suggested pose, captured, is decoded by every camera it
names (checked through the service, the poses placed by the simulator's truth)."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from hw_mocks.truth import SimulatorTruth
from tests.api.test_rig_calibration_api import CONFIG, finished


@pytest.fixture(scope="module")
def rig_session(tmp_path_factory: pytest.TempPathFactory):
    data = tmp_path_factory.mktemp("rigguide") / "data"
    with TestClient(create_app(ServiceConfig(data_dir=data, executor="threads"))) as c:
        rig = c.post("/rigs", json={"name": "pair", "config": CONFIG}).json()
        sess = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()
        yield c, sess["id"]


def _capture(c: TestClient, sid: str, pose: dict) -> dict:
    job = finished(c, c.post(f"/sessions/{sid}/poses", json={"screen_pose": pose}).json()["id"])
    assert job["status"] == "succeeded", job["error"]
    return c.get(job["resource"]).json()


def test_next_pose_on_a_rig_names_the_cameras_it_serves(rig_session) -> None:
    c, sid = rig_session
    poses = SimulatorTruth.from_config(CONFIG).screen_poses(4, seed=3)
    for pose in poses[:2]:
        _capture(c, sid, pose)
    r = c.get(f"/sessions/{sid}/next-pose", params={"model": "opencv5"})
    assert r.status_code == 409 and "needs >= 3 decoded poses of every camera" in r.text, r.text
    for pose in poses[2:]:
        _capture(c, sid, pose)
    r = c.get(f"/sessions/{sid}/next-pose", params={"model": "opencv5"})
    assert r.status_code == 200, r.text
    out = r.json()
    assert [cam["camera"] for cam in out["cameras"]] == ["left", "right"]
    assert out["shared_views"] == [{"cameras": ["left", "right"], "views": 4}]
    assert out["weakly_tied"] == [] and out["serves"]
    for cam in out["cameras"]:
        sigma = cam["predicted_worst_ray_sigma_urad"]
        assert sigma["now"] > 0 and cam["views"] == 4
        assert cam["serves"] == (cam["camera"] in out["serves"])
        if cam["serves"]:
            assert sigma["after"] < sigma["now"]
    rig_worst = max(cam["predicted_worst_ray_sigma_urad"]["now"] for cam in out["cameras"])
    assert out["predicted_worst_ray_sigma_urad"]["now"] == pytest.approx(rig_worst)
    captured = _capture(c, sid, out["screen_pose"])
    valid = {cam["name"]: cam.get("valid_pixels", 0) for cam in captured["cameras"]}
    for name in out["serves"]:
        assert valid[name] > 200, (name, valid)
