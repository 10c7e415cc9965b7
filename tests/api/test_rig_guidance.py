"""Next-pose guidance on a session of two simulated cameras: the suggestion names the
cameras it serves with each camera's predicted worst ray sigma now and after, counts the
views the pair shares, gives each served camera the screen's outline in its pixels and each
camera a picture, and the suggested pose, captured, is decoded by every camera it names
where its outline said (checked through the service, the poses placed by the simulator's
truth); `phasecal guide` on the same maps as CAMERA/VIEW=PATH answers as the route."""

from __future__ import annotations

import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from api.app import create_app
from api.cli import main as cli_main
from api.config import ServiceConfig
from hw_mocks.truth import SimulatorTruth
from tests.api.test_rig_calibration_api import CONFIG, finished

SIZES = {c["name"]: (c["width"], c["height"]) for c in CONFIG["cameras"]}


@pytest.fixture(scope="module")
def rig_session(tmp_path_factory: pytest.TempPathFactory):
    data = tmp_path_factory.mktemp("rigguide") / "data"
    with TestClient(create_app(ServiceConfig(data_dir=data, executor="threads"))) as c:
        rig = c.post("/rigs", json={"name": "pair", "config": CONFIG}).json()
        sess = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()
        yield c, sess["id"], data


@pytest.fixture(scope="module")
def planned(rig_session) -> dict:
    """The next pose after four poses (and the refusal after two on the way)."""
    c, sid, _ = rig_session
    poses = SimulatorTruth.from_config(CONFIG).screen_poses(4, seed=3)
    for pose in poses[:2]:
        _capture(c, sid, pose)
    r = c.get(f"/sessions/{sid}/next-pose", params={"model": "opencv5"})
    assert r.status_code == 409 and "needs >= 3 decoded poses of every camera" in r.text, r.text
    for pose in poses[2:]:
        _capture(c, sid, pose)
    r = c.get(f"/sessions/{sid}/next-pose", params={"model": "opencv5"})
    assert r.status_code == 200, r.text
    return r.json()


def _capture(c: TestClient, sid: str, pose: dict) -> dict:
    job = finished(c, c.post(f"/sessions/{sid}/poses", json={"screen_pose": pose}).json()["id"])
    assert job["status"] == "succeeded", job["error"]
    return c.get(job["resource"]).json()


def _in_image(outline: list, size: tuple[int, int]) -> float:
    """Pixels of the image inside the outline (its corners may reach past the edge)."""
    w, h = size
    frame = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float32)
    hull = cv2.convexHull(np.asarray(outline, np.float32))
    return float(cv2.intersectConvexConvex(hull, frame)[0])


def test_next_pose_on_a_rig_names_the_cameras_it_serves(rig_session, planned) -> None:
    c, sid, _ = rig_session
    out = planned
    assert [cam["camera"] for cam in out["cameras"]] == ["left", "right"]
    assert out["shared_views"] == [{"cameras": ["left", "right"], "views": 4}]
    assert out["weakly_tied"] == [] and out["serves"]
    for cam in out["cameras"]:
        sigma = cam["predicted_worst_ray_sigma_urad"]
        assert sigma["now"] > 0 and cam["views"] == 4
        assert cam["serves"] == (cam["camera"] in out["serves"])
        assert (cam["outline_px"] is not None) == cam["serves"]
        if cam["serves"]:
            assert sigma["after"] < sigma["now"]
            assert len(cam["outline_px"]) == 4
            assert _in_image(cam["outline_px"], SIZES[cam["camera"]]) > 0.1 * np.prod(
                SIZES[cam["camera"]])
    rig_worst = max(cam["predicted_worst_ray_sigma_urad"]["now"] for cam in out["cameras"])
    assert out["predicted_worst_ray_sigma_urad"]["now"] == pytest.approx(rig_worst)
    captured = _capture(c, sid, out["screen_pose"])
    valid = {cam["name"]: cam.get("valid_pixels", 0) for cam in captured["cameras"]}
    for cam in out["cameras"]:
        if cam["serves"]:  # the camera decodes the screen where its outline put it
            inside = _in_image(cam["outline_px"], SIZES[cam["camera"]])
            assert 0.8 * inside < valid[cam["camera"]] < 1.1 * inside, (cam, valid)


def test_rig_next_pose_pictures_one_per_camera(rig_session, planned) -> None:
    c, sid, _ = rig_session
    key = planned["key"]
    pictures = []
    for cam in planned["cameras"]:
        assert cam["image"] == f"/sessions/{sid}/next-pose.png?camera={cam['camera']}&key={key}"
        r = c.get(cam["image"])
        assert r.status_code == 200 and r.headers["content-type"] == "image/png", r.text
        assert "immutable" in r.headers["cache-control"]
        img = np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB"), dtype=float)
        assert img.shape[0] > 200 and img.std() > 20
        pictures.append(img)
    assert not np.array_equal(*pictures[:2])  # each camera its own map and title
    current = c.get(f"/sessions/{sid}/next-pose.png", params={"camera": "right",
                                                              "model": "opencv5"})
    assert current.status_code == 200 and current.headers["cache-control"] == "no-cache"
    assert current.content[:4] == b"\x89PNG"
    for query, named in (({"camera": "middle", "key": key}, "left, right"),
                         ({"key": key}, "left, right"),
                         ({"camera": "left", "key": "0123456789abcdef"}, "no next-pose plan")):
        r = c.get(f"/sessions/{sid}/next-pose.png", params=query)
        assert r.status_code == 404 and r.headers["content-type"] == "application/problem+json"
        assert named in r.json()["detail"], r.text


def test_the_guide_command_plans_a_rig_as_the_route(rig_session, planned, tmp_path: Path
                                                     ) -> None:
    _, sid, data = rig_session
    maps = [f"{cam}/{pid}={data / 'poses' / pid / 'cameras' / cam / 'maps.npz'}"
            for pid in planned["poses_used"] for cam in SIZES]
    plan = str(data / "sessions" / sid / "plan.json")
    out, pictures = tmp_path / "guide.json", tmp_path / "pictures"
    assert cli_main(["guide", "--plan", plan, "--maps", *maps, "--model", "opencv5",
                     "--png-dir", str(pictures), "-o", str(out)]) == 0
    body = json.loads(out.read_text())["next_pose"]
    assert body["serves"] == planned["serves"] and body["reference"] == "left"
    assert body["screen_pose"]["tvec_mm"] == pytest.approx(planned["screen_pose"]["tvec_mm"])
    for cam, route in zip(body["cameras"], planned["cameras"], strict=True):
        assert cam["outline_px"] == route["outline_px"]
        assert Path(cam["image"]) == pictures / f"next-pose-{cam['camera']}.png"
        assert Path(cam["image"]).read_bytes()[:4] == b"\x89PNG"
    for wrong in (["--image", str(tmp_path / "n.png")], ["--reference", "middle"]):
        assert cli_main(["guide", "--plan", plan, "--maps", *maps, *wrong]) == 1
    assert cli_main(["guide", "--plan", plan, "--maps", *maps[:4]]) == 1  # 2 poses a camera
