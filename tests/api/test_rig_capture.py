"""A rig of several cameras through the service: configs over REST, a pose captured on three
simulated cameras in sync (one camera's maps per camera, each checked against that camera's
truth), a camera dropping a frame, and the per-camera maps and status of a pose."""

from __future__ import annotations

import io
import json
import time
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from acquisition.patterns import build_plan
from acquisition.rig import open_rig, parse_rig_config
from api.app import create_app
from api.config import ServiceConfig
from api.pose_path import (
    ThreadRigDecode,
    camera_dirs,
    capture_rig_live,
    stored_indices,
    write_camera_names,
)
from api.worker.tasks import stream_decode_rig_task
from calibration.decode import DecodeError
from calibration.shared.frame_store import FrameStore
from calibration.shared.maps import load_maps
from calibration.shared.progress import TaskContext
from hw_mocks.rig import open_simulated_rig
from hw_mocks.truth import SimulatorTruth

SCREEN = {"width_px": 320, "height_px": 240, "pitch_mm": [0.5, 0.5]}


def three_camera_rig(**right: object) -> dict:
    """Three simulated cameras: different sizes, lenses and timing, placed around one."""
    return {"kind": "simulated", "screen": SCREEN, "cameras": [
        {"name": "left", "model": "mild_pinhole", "width": 96, "height": 72},
        {"name": "right", "model": "mild_pinhole", "width": 112, "height": 84,
         "trigger_latency_s": 1e-3, "timestamp_jitter_s": 3e-4, **right},
        {"name": "top", "model": "smooth_noncentral", "width": 80, "height": 60,
         "timestamp_jitter_s": 1e-4},
    ]}


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory):
    data = tmp_path_factory.mktemp("rig") / "data"
    with TestClient(create_app(ServiceConfig(data_dir=data, executor="threads"))) as c:
        yield c, data


def _finished(c: TestClient, job_id: str, timeout_s: float = 300) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = c.get(f"/jobs/{job_id}").json()
        if job["status"] not in ("queued", "running"):
            return job
        time.sleep(0.02)
    raise AssertionError(f"job {job_id} did not finish")


def _capture(c: TestClient, config: dict, name: str) -> tuple[dict, dict]:
    rig = c.post("/rigs", json={"name": name, "config": config})
    assert rig.status_code == 201, rig.text
    sess = c.post("/sessions", json={"rig_id": rig.json()["id"], "preset": "fast"}).json()
    job = _finished(c, c.post(f"/sessions/{sess['id']}/poses", json={}).json()["id"])
    assert job["status"] == "succeeded", job["error"]
    return job, c.get(job["resource"]).json()


def test_rig_configs_over_rest_are_validated(service) -> None:
    c, _ = service
    rig = c.post("/rigs", json={"name": "trio", "config": three_camera_rig()})
    assert rig.status_code == 201, rig.text
    stored = c.get(f"/rigs/{rig.json()['id']}").json()["config"]
    assert [cam["name"] for cam in stored["cameras"]] == ["left", "right", "top"]
    assert stored["camera"] is None
    settings = f"/rigs/{rig.json()['id']}/camera/settings"
    changed = c.put(settings, params={"camera": "right"}, json={"exposure_s": 0.005})
    assert changed.status_code == 200 and changed.json()["exposure_s"] == 0.005
    assert c.get(settings, params={"camera": "right"}).json()["exposure_s"] == 0.005
    assert c.get(settings).json()["exposure_s"] != 0.005  # the reference's are its own
    unknown = c.get(settings, params={"camera": "back"})
    assert unknown.status_code == 422 and unknown.json()["field"] == "camera"
    twice = three_camera_rig()
    twice["cameras"][2]["name"] = "left"
    bad = c.post("/rigs", json={"name": "twice", "config": twice})
    assert bad.status_code == 422 and "duplicate camera name(s) ['left']" in bad.json()["detail"]
    webcam = three_camera_rig()
    webcam["cameras"][1]["backend"] = "webcam"
    bad = c.post("/rigs", json={"name": "webcam", "config": webcam})
    assert bad.status_code == 422 and "cameras.1" in bad.json()["detail"]
    huge = three_camera_rig(width=8192, height=8192)
    bad = c.post("/rigs", json={"name": "huge", "config": huge})
    assert bad.status_code == 422 and bad.json()["field"] == "config.cameras.1.width"


def test_a_rig_over_rest_shows_its_mover_and_may_not_name_a_robot_server(service) -> None:
    c, _ = service
    arm = {"backend": "simulated-arm", "timeout_s": 20, "speed_mm_s": 500}
    rig = c.post("/rigs", json={"name": "armed", "config": {**three_camera_rig(), "mover": arm}})
    assert rig.status_code == 201, rig.text
    shown = c.get(f"/rigs/{rig.json()['id']}").json()["config"]["mover"]
    assert shown["backend"] == "simulated-arm" and shown["timeout_s"] == 20
    assert shown["speed_mm_s"] == 500 and shown["workspace"] is None
    # the arm carries the camera: the view follows it, so nothing places the screen by hand
    placed = {"rvec": [0.0, 0.0, 0.0], "tvec_mm": [0.0, 0.0, 400.0]}
    moved = c.put(f"/rigs/{rig.json()['id']}/screen-pose", json=placed)
    assert moved.status_code == 409 and moved.json()["type"].endswith("view-follows-mover")
    assert "carries its camera on its mover" in moved.json()["detail"]
    sess = c.post("/sessions", json={"rig_id": rig.json()["id"]}).json()
    refused = c.post(f"/sessions/{sess['id']}/poses", json={"screen_pose": placed})
    assert refused.status_code == 409 and "automatic run" in refused.json()["detail"]
    assert c.get(f"/sessions/{sess['id']}/poses").json() == []  # no pose, no job left behind
    http = {**three_camera_rig(), "mover": {"backend": "http", "url": "http://10.0.0.7:8100"}}
    bad = c.post("/rigs", json={"name": "remote", "config": http})
    assert bad.status_code == 422 and bad.json()["field"] == "config.mover.url"
    assert "a robot server cannot be named over REST" in bad.json()["detail"]
    wrong = {**three_camera_rig(), "mover": {"backend": "simulated-linear", "travel_mm": [5, 1]}}
    bad = c.post("/rigs", json={"name": "rail", "config": wrong})
    assert bad.status_code == 422 and "travel_mm: low 5 exceeds high 1" in bad.json()["detail"]


def test_three_cameras_give_three_maps_matching_each_cameras_truth(service) -> None:
    c, data = service
    config = three_camera_rig()
    job, pose = _capture(c, config, "sync")
    cap = job["result"]["capture"]
    assert cap["recaptures"] == 0 and set(cap["cameras"]) == {"left", "right", "top"}
    assert [cam["name"] for cam in pose["cameras"]] == ["left", "right", "top"]
    assert all(cam["status"] == "ready" for cam in pose["cameras"]), pose["cameras"]
    truth = SimulatorTruth.from_config(config)
    for cam in pose["cameras"]:
        info = next(cc for cc in config["cameras"] if cc["name"] == cam["name"])
        assert (cam["width"], cam["height"]) == (info["width"], info["height"])
        r = c.get(f"{job['resource']}/maps.npz", params={"camera": cam["name"]})
        assert r.status_code == 200
        maps = load_maps(r.content)
        assert maps.shape == (info["height"], info["width"])
        assert maps.meta["camera_name"] == cam["name"] and maps.valid_count() == cam["valid_pixels"]
        x_true, _ = truth.screen_points(None, cam["name"])
        assert maps.mask.sum() > 0.5 * np.isfinite(x_true).sum(), cam["name"]
        assert np.median(np.abs((maps.x - x_true)[maps.mask])) < 0.2  # screen px
        errors = truth.normalized_errors(maps, None, cam["name"])
        assert 0.5 < np.std(errors) < 2.0, cam["name"]  # each camera's own truth, not another's
        assert (data / "poses" / pose["id"] / "cameras" / cam["name"] / "maps.npz").is_file()
    png = c.get(f"{job['resource']}/preview/x.png", params={"camera": "top"})
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    missing = c.get(f"{job['resource']}/maps.npz")
    assert missing.status_code == 422 and missing.json()["field"] == "camera"
    assert "['left', 'right', 'top']" in missing.json()["detail"]
    unknown = c.get(f"{job['resource']}/maps.npz", params={"camera": "back"})
    assert unknown.status_code == 422 and "'back' is not a camera" in unknown.json()["detail"]


def test_a_camera_dropping_a_frame_gets_its_pattern_shown_again(service) -> None:
    c, _ = service
    job, pose = _capture(c, three_camera_rig(lost_triggers=[6]), "drop")
    cap = job["result"]["capture"]
    assert cap["recaptures"] == 1 and cap["lost_frames"] == 1
    assert cap["cameras"]["right"]["lost_frames"] == 1
    assert cap["cameras"]["left"]["recaptures"] == 0
    assert pose["status"] == "ready" and pose["frames_done"] == cap["captured"]
    for cam in pose["cameras"]:
        assert cam["status"] == "ready" and cam["valid_pixels"] > 0


def test_a_one_camera_pose_keeps_its_layout(service, tmp_path: Path) -> None:
    c, data = service
    config = {"kind": "simulated", "screen": SCREEN,
              "camera": {"model": "mild_pinhole", "width": 64, "height": 48}}
    job, pose = _capture(c, config, "single")
    assert pose["cameras"] is None and pose["status"] == "ready"
    pose_dir = data / "poses" / pose["id"]
    assert (pose_dir / "maps.npz").is_file() and not (pose_dir / "cameras").exists()
    assert c.get(f"{job['resource']}/maps.npz").status_code == 200
    wrong = c.get(f"{job['resource']}/maps.npz", params={"camera": "cam0"})
    assert wrong.status_code == 422 and "leave camera out" in wrong.json()["detail"]


def test_one_cameras_frames_are_decoded_again_and_exported(service) -> None:
    """Re-decode and frames.zip of a several-camera pose name the camera (a missing or
    unknown one is refused naming the pose's cameras); a re-decode replaces that camera's
    maps only."""
    c, data = service
    config = {"kind": "simulated", "screen": SCREEN, "cameras": [
        {"name": "near", "width": 64, "height": 48},
        {"name": "far", "width": 72, "height": 54}]}
    job, pose = _capture(c, config, "redecode")
    url, cameras = job["resource"], data / "poses" / pose["id"] / "cameras"
    listed = c.get(url.rsplit("/", 1)[0]).json()
    assert [cam["name"] for cam in listed[0]["cameras"]] == ["near", "far"]
    for route, method in (("decode", c.post), ("frames.zip", c.get)):
        missing = method(f"{url}/{route}")
        assert missing.status_code == 422 and missing.json()["field"] == "camera"
        assert "['near', 'far']" in missing.json()["detail"], route
        unknown = method(f"{url}/{route}", params={"camera": "back"})
        assert unknown.status_code == 422 and "'back' is not a camera" in unknown.json()["detail"]
    near_before = (cameras / "near" / "maps.npz").read_bytes()
    far_before = load_maps(cameras / "far" / "maps.npz")
    median = float(np.median(far_before.sigma_x[far_before.mask]))
    again = c.post(f"{url}/decode", params={"camera": "far"},
                   json={"options": {"max_sigma_px": float(f"{median:.4g}")}})
    assert again.status_code == 202, again.text
    done = _finished(c, again.json()["id"])
    assert done["status"] == "succeeded", done["error"]
    far = load_maps(c.get(f"{url}/maps.npz", params={"camera": "far"}).content)
    assert far.meta["redecoded"] is True and far.meta["camera_name"] == "far"
    assert 0 < far.valid_count() < far_before.valid_count()  # the tighter sigma limit
    assert (cameras / "near" / "maps.npz").read_bytes() == near_before
    after = c.get(url).json()
    assert after["status"] == "ready" and after["valid_pixels"] == pose["valid_pixels"]
    assert {cam["name"]: cam["valid_pixels"] for cam in after["cameras"]}["far"] \
        == far.valid_count()
    exported = c.get(f"{url}/frames.zip", params={"camera": "far"})
    assert exported.status_code == 200
    assert f'{pose["id"]}-far-frames.zip' in exported.headers["content-disposition"]
    with zipfile.ZipFile(io.BytesIO(exported.content)) as zf:
        names = zf.namelist()
        first = cv2.imdecode(np.frombuffer(zf.read(names[0]), np.uint8), cv2.IMREAD_UNCHANGED)
    assert len(names) == pose["frames_done"] and first.shape == (54, 72)


def test_capture_on_several_cameras_outside_the_service_and_resume(tmp_path: Path) -> None:
    """The live pose path for `phasecal capture`: every camera into its folder's store while
    a thread decodes them all; a second run finds every frame stored and captures none."""
    rig = open_rig(parse_rig_config(three_camera_rig()), simulator=open_simulated_rig)
    plan = build_plan(320, 240, [0.5, 0.5], preset="fast")
    plan_path = tmp_path / "plan.json"
    plan_path.write_text(json.dumps(plan.to_dict()))
    names = list(rig.cameras)
    write_camera_names(tmp_path, names)
    dirs = camera_dirs(tmp_path, names)
    try:
        for run in range(2):
            decode = ThreadRigDecode(plan_path, {n: (dirs[n], dirs[n] / "maps.npz",
                                                     {"camera_name": n}) for n in names})
            cap = capture_rig_live(TaskContext("capture"), rig, plan, dirs, decode)
            result = decode.result()
            assert cap["captured"] == (len(plan.frames) if run == 0 else 0)
            assert set(result) == set(names)
    finally:
        rig.close()
    assert stored_indices(tmp_path) == set(range(len(plan.frames)))
    for name in names:
        maps = load_maps(dirs[name] / "maps.npz")
        info = rig.cameras[name].info
        assert maps.shape == (info.height, info.width) and maps.valid_count() > 0


def test_one_cameras_failed_decode_stops_the_others(tmp_path: Path) -> None:
    """A camera whose store holds frames of another plan fails its decode; the decodes of
    the cameras still waiting for frames stop too, and the failure (not their cancel) is
    what the task raises."""
    plan = build_plan(320, 240, [0.5, 0.5], preset="fast")
    plan_path = tmp_path / "plan.json"
    plan_path.write_text(json.dumps(plan.to_dict()))
    wrong = FrameStore(tmp_path / "bad", len(plan.frames) + 1)
    wrong.add(0, np.zeros((4, 6), np.uint8))
    wrong.flush()
    cameras = {"bad": (str(tmp_path / "bad"), str(tmp_path / "bad.npz"), {}),
               "idle": (str(tmp_path / "idle"), str(tmp_path / "idle.npz"), {})}
    with pytest.raises(DecodeError):
        stream_decode_rig_task(TaskContext("job"), str(plan_path), cameras)
    assert not (tmp_path / "idle.npz").exists()
