"""A whole session over HTTP on the simulated rig, against a real uvicorn subprocess.

Capture (moving the simulated screen over the API), calibrate, exports, project /
unproject against the simulator's truth, cancel, and restart recovery after kill -9.
Small images (160x120 camera, small screen) keep it fast.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from api.client import PhasecalClient, ServiceError
from api.demo import demo_rig_config
from calibration.models.base import model_from_dict
from calibration.shared.maps import load_maps
from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import mild_pinhole
from hw_mocks.poses import random_poses
from tests.api_server import ServerProcess

W, H = 160, 120
SCREEN = ScreenGeometry(320, 240, (0.5, 0.5))


def small_rig(slow: bool = False) -> dict:
    """A simulated rig with a small mild-pinhole camera and a small screen.

    `slow`: 320x240 with 4x4 supersampled rendering (~50 ms a frame or more), so that a
    capture runs long enough to be cancelled or killed mid-sequence.
    """
    if slow:
        cfg = demo_rig_config(2 * W, 2 * H, camera="mild_pinhole", screen=SCREEN)
        cfg["camera"]["supersample"] = 4
        return cfg
    return demo_rig_config(W, H, camera="mild_pinhole", screen=SCREEN)


def truth_camera():
    return mild_pinhole(W, H)


def screen_poses(n: int, seed: int) -> list[dict]:
    out = []
    for p in random_poses(truth_camera(), SCREEN, n, np.random.default_rng(seed)):
        rvec, _ = cv2.Rodrigues(np.asarray(p.rotation, np.float64))
        out.append({"rvec": rvec.ravel().tolist(), "tvec_mm": np.asarray(p.translation).tolist()})
    return out


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):
    srv = ServerProcess(tmp_path_factory.mktemp("session") / "data")
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def client(server: ServerProcess):
    c = PhasecalClient(server.url)
    yield c
    c.close()


@pytest.fixture(scope="module")
def session(client: PhasecalClient) -> dict:
    rig = client.post("/rigs", {"name": "small", "config": small_rig()})
    return client.post("/sessions", {"name": "whole", "rig_id": rig["id"], "preset": "fast"})


@pytest.fixture(scope="module")
def captured(client: PhasecalClient, session: dict) -> list[str]:
    ids = []
    for pose in screen_poses(4, seed=11):
        job = client.wait(client.post(f"/sessions/{session['id']}/poses",
                                      {"screen_pose": pose}), timeout_s=300)
        assert job["status"] == "succeeded", job["error"]
        ids.append(job["resource"].rsplit("/", 1)[-1])
    return ids


def test_capture_poses(client: PhasecalClient, session: dict, captured: list[str]) -> None:
    poses = client.get(f"/sessions/{session['id']}/poses")
    assert [p["id"] for p in poses] == captured
    for p in poses:
        assert p["status"] == "ready" and p["source"] == "capture"
        assert (p["width"], p["height"]) == (W, H) and p["valid_pixels"] > 0.1 * W * H
        assert p["frames_done"] == session["frame_count"]
    data = client.request("GET", f"/sessions/{session['id']}/poses/{captured[0]}/maps.npz")
    maps = load_maps(data.content)
    assert maps.meta["pose_id"] == captured[0]


def test_calibrate_export_project(client: PhasecalClient, session: dict,
                                  captured: list[str]) -> None:
    job = client.post(f"/sessions/{session['id']}/calibrations",
                      {"model": "opencv5", "pose_ids": captured[:3],
                       "heldout_pose_ids": captured[3:]})
    final = client.wait(job, timeout_s=300)
    assert final["status"] == "succeeded", final["error"]
    cal = client.get(final["resource"])
    assert cal["stats"]["rms_px"] < 0.5
    for name in ("model.json", "result.json", "opencv.yaml", "camera_info.yaml", "residuals.png"):
        assert name in cal["exports"]
        r = client.request("GET", f"/calibrations/{cal['id']}/files/{name}")
        assert len(r.content) > 50
    model = model_from_dict(client.get(f"/calibrations/{cal['id']}/files/model.json"))
    assert model.image_size == (W, H)
    # project/unproject agree with each other and with the simulator's truth
    u, v = np.meshgrid(np.linspace(10, W - 10, 7), np.linspace(10, H - 10, 5))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    rays = client.post(f"/calibrations/{cal['id']}/unproject", {"pixels": pixels.tolist()})
    dirs = np.asarray(rays["directions"], float)
    _, true_dirs = truth_camera().rays(pixels[:, 0], pixels[:, 1])
    angle = np.arccos(np.clip(np.sum(dirs * true_dirs, axis=1), -1, 1))
    assert np.median(angle) < 2e-3
    back = client.post(f"/calibrations/{cal['id']}/project",
                       {"points": (dirs * 500.0).tolist()})
    assert np.allclose(np.asarray(back["pixels"], float), pixels, atol=1e-3)


def test_cancel_and_resume(client: PhasecalClient, server: ServerProcess) -> None:
    rig = client.post("/rigs", {"name": "slow", "config": small_rig(slow=True)})
    sess = client.post("/sessions", {"rig_id": rig["id"], "preset": "fast"})
    job = client.post(f"/sessions/{sess['id']}/poses", {"screen_pose": screen_poses(1, 5)[0]})
    _wait_until(client, job["id"], lambda j: j["stage"] == "capture" and j["done"] >= 3)
    client.post(f"/jobs/{job['id']}/cancel")
    final = client.wait(job, check=False)
    assert final["status"] == "cancelled"
    pose = client.get(final["resource"])
    assert pose["status"] == "cancelled"
    again = client.wait(client.post(f"{final['resource']}/resume"), timeout_s=300)
    assert again["status"] == "succeeded", again["error"]
    assert again["result"]["capture"]["resumed_from"] >= 3
    assert client.get(final["resource"])["status"] == "ready"


def _wait_until(client: PhasecalClient, job_id: str, cond, timeout_s: float = 120) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        j = client.get(f"/jobs/{job_id}")
        if cond(j):
            return j
        assert j["status"] in ("queued", "running"), j
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not reach the condition")


def test_restart_recovery(tmp_path) -> None:
    srv = ServerProcess(tmp_path / "data")
    srv.start()
    c = PhasecalClient(srv.url)
    try:
        fast = c.post("/rigs", {"name": "fast", "config": small_rig()})
        first = c.post("/sessions", {"rig_id": fast["id"], "preset": "fast"})
        done = c.wait(c.post(f"/sessions/{first['id']}/poses",
                             {"screen_pose": screen_poses(2, 9)[0]}), timeout_s=300)
        assert done["status"] == "succeeded"
        rig = c.post("/rigs", {"name": "slow", "config": small_rig(slow=True)})
        sess = c.post("/sessions", {"rig_id": rig["id"], "preset": "fast"})
        job = c.post(f"/sessions/{sess['id']}/poses", {"screen_pose": screen_poses(2, 9)[1]})
        _wait_until(c, job["id"], lambda j: j["stage"] == "capture" and j["done"] >= 3)
        srv.kill()
        c.close()
        srv.start()
        c = PhasecalClient(srv.url)
        j = c.get(f"/jobs/{job['id']}")
        assert j["status"] == "interrupted" and "server stopped" in j["error"]
        pose = c.get(j["resource"])
        assert pose["status"] == "interrupted" and "restart" in pose["error"]
        finished = c.get(done["resource"])
        assert finished["status"] == "ready"
        maps = load_maps(c.request("GET", f"{done['resource']}/maps.npz").content)
        assert maps.valid_count() == finished["valid_pixels"]
        with pytest.raises(ServiceError, match="409"):
            c.post(f"{done['resource']}/resume")
        resumed = c.wait(c.post(f"{j['resource']}/resume"), timeout_s=300)
        assert resumed["status"] == "succeeded", resumed["error"]
        assert resumed["result"]["capture"]["resumed_from"] >= 3
        assert c.get(j["resource"])["status"] == "ready"
    finally:
        c.close()
        srv.stop()


def test_generic_options_through_the_api(client: PhasecalClient, session: dict,
                                         captured: list[str]) -> None:
    """sGCC options pass through the REST job unchanged: the mesh chosen on validation points
    is reported, and a malformed option is refused at the request (422 naming the field)."""
    final = client.wait(client.post(f"/sessions/{session['id']}/calibrations",
                                    {"model": "sgcc", "pose_ids": captured,
                                     "options": {"cells": "auto"}}), timeout_s=300)
    assert final["status"] == "succeeded", final["error"]
    stats = client.get(final["resource"])["stats"]
    tried = [r["cells"] for r in stats["mesh_choice"]]
    assert tried == [[10, 8], [14, 10], [20, 15]][: len(tried)] and stats["cells"] in tried
    assert isinstance(stats["warnings"], list) and len(stats["views_per_pixel"]) == 4
    with pytest.raises(ServiceError) as bad:
        client.post(f"/sessions/{session['id']}/calibrations",
                    {"model": "sgcc", "pose_ids": captured, "options": {"xp": "torch"}})
    assert bad.value.status == 422 and "options.xp" in str(bad.value)


@pytest.mark.parametrize("model", ["opencv5", "sgcc-noncentral"])
def test_screen_options_through_the_api(client: PhasecalClient, session: dict,
                                        captured: list[str], model: str) -> None:
    """A parametric or sGCC REST job takes `screen: "fit"` and `glass_index`: the screen
    estimate with its 1-sigma is stored with the calibration; a bad value is a 422 naming
    the option."""
    extra = {"cells": [6, 6]} if model.startswith("sgcc") else {}
    final = client.wait(client.post(f"/sessions/{session['id']}/calibrations",
                                    {"model": model, "pose_ids": captured,
                                     "options": {"screen": "fit", "glass_index": 1.5, **extra}}),
                        timeout_s=300)
    assert final["status"] == "succeeded", final["error"]
    scr = client.get(final["resource"])["stats"]["screen"]
    assert scr["mode"] == "fit" and scr["glass_index"] == 1.5
    assert set(scr["std"]) == {"bow_x_mm", "bow_y_mm", "twist_mm", "glass_mm"}
    with pytest.raises(ServiceError) as bad:
        client.post(f"/sessions/{session['id']}/calibrations",
                    {"model": model, "pose_ids": captured, "options": {"glass_index": 9}})
    assert bad.value.status == 422 and "glass_index" in str(bad.value)
