"""A captured pose is ready before its maps are fsynced; what a crash then leaves is safe.

The maps are committed with a durable `maps.pending` mark and fsynced in the background.
A restart after a crash that kept the page cache (a killed server) finds intact maps and
keeps the pose; a restart after a power cut that lost part of the file finds a CRC
mismatch (or no archive at all), removes the maps and marks the pose `interrupted`, and
resuming it decodes its durable frames again into the same maps.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from api.maps_durability import PENDING, intact_maps
from calibration.shared.maps import load_maps
from tests.api.test_api_session import screen_poses, small_rig


def _wait_done(c: TestClient, job_id: str, timeout_s: float = 300) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        j = c.get(f"/jobs/{job_id}").json()
        if j["status"] not in ("queued", "running"):
            return j
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not end")


def _app(data: Path):
    return create_app(ServiceConfig(data_dir=data, executor="threads"))


def _capture_one(c: TestClient) -> dict:
    """Capture one pose on a small simulated rig; its finished job."""
    rig = c.post("/rigs", json={"name": "small", "config": small_rig()}).json()
    sess = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()
    job = c.post(f"/sessions/{sess['id']}/poses",
                 json={"screen_pose": screen_poses(1, 3)[0]}).json()
    final = _wait_done(c, job["id"])
    assert final["status"] == "succeeded", final["error"]
    return final


@pytest.fixture(scope="module")
def captured(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str, bytes]:
    """A data folder with one captured, ready pose (server stopped): (data, pose url, maps)."""
    data = tmp_path_factory.mktemp("durable") / "data"
    with TestClient(_app(data)) as c:
        final = _capture_one(c)
        pose = c.get(final["resource"]).json()
        assert pose["status"] == "ready"
        maps = c.get(f"{final['resource']}/maps.npz").content  # served at once after ready
        c.app.state.services.maps_sync.drain()
        pose_dir = data / "poses" / pose["id"]
        assert not (pose_dir / PENDING).exists()  # durable: the mark is gone
        assert (pose_dir / "maps.npz").read_bytes() == maps
    return data, final["resource"], maps


def _crash_state(data: Path, pose_url: str, damage: str, maps: bytes) -> Path:
    """Leave the pose folder as a crash before the background fsync could have left it."""
    return _crash_maps(data / "poses" / pose_url.rsplit("/", 1)[1], damage, maps)


def _crash_maps(pose_dir: Path, damage: str, maps: bytes) -> Path:
    """Leave a folder of maps (a pose's, or a camera's of a pose) as such a crash would."""
    (pose_dir / PENDING).touch()
    path = pose_dir / "maps.npz"
    if damage == "killed":  # page cache kept: the whole file
        path.write_bytes(maps)
    elif damage == "truncated":  # the size never reached the disk
        path.write_bytes(maps[: len(maps) // 3])
    elif damage == "zeroed":  # the size did, some data blocks did not (they read as zeros)
        raw = bytearray(maps)
        raw[len(raw) // 2: len(raw) // 2 + 4096] = bytes(4096)
        path.write_bytes(bytes(raw))
    return pose_dir


def test_a_killed_server_keeps_intact_pending_maps(captured: tuple[Path, str, bytes]) -> None:
    data, pose_url, maps = captured
    pose_dir = _crash_state(data, pose_url, "killed", maps)
    with TestClient(_app(data)) as c:
        pose = c.get(pose_url).json()
        assert pose["status"] == "ready"
        assert not (pose_dir / PENDING).exists()
        assert c.get(f"{pose_url}/maps.npz").content == maps


@pytest.mark.parametrize("damage", ["truncated", "zeroed"])
def test_maps_lost_before_durable_are_not_trusted_and_redecoded(
        captured: tuple[Path, str, bytes], damage: str) -> None:
    data, pose_url, maps = captured
    pose_dir = _crash_state(data, pose_url, damage, maps)
    assert intact_maps(pose_dir / "maps.npz") is not None  # the damage is detectable
    with TestClient(_app(data)) as c:
        pose = c.get(pose_url).json()
        assert pose["status"] == "interrupted" and "not yet durable" in pose["error"]
        assert not (pose_dir / "maps.npz").exists() and not (pose_dir / PENDING).exists()
        assert c.get(f"{pose_url}/maps.npz").status_code == 409
        job = c.post(f"{pose_url}/resume").json()  # frames are durable: decode them again
        final = _wait_done(c, job["id"])
        assert final["status"] == "succeeded", final["error"]
        assert final["result"]["capture"]["captured"] == 0
        assert c.get(pose_url).json()["status"] == "ready"
        again, before = load_maps(c.get(f"{pose_url}/maps.npz").content), load_maps(maps)
        c.app.state.services.maps_sync.drain()
    assert not (pose_dir / PENDING).exists()
    for name in ("x", "y", "sigma_x", "sigma_y", "mask"):
        np.testing.assert_array_equal(getattr(again, name), getattr(before, name))


def test_a_flagged_pose_stays_flagged_when_its_lost_maps_are_decoded_again(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The integrity check cannot be repeated after the pose; its verdict is kept with the
    frames, so resuming a flagged pose whose maps were lost gives a flagged pose again."""
    import api.pose_path as capture
    from api.pose_path import VERDICT

    real = capture.capture_pose

    def moved(*args, **kwargs):  # the check of this capture found the screen moved
        return dataclasses.replace(real(*args, **kwargs), status="flagged",
                                   reason="camera or screen moved")

    monkeypatch.setattr(capture, "capture_pose", moved)
    data = tmp_path / "data"
    with TestClient(_app(data)) as c:
        final = _capture_one(c)
        assert c.get(final["resource"]).json()["status"] == "flagged"
        maps = c.get(f"{final['resource']}/maps.npz").content
        c.app.state.services.maps_sync.drain()
    monkeypatch.setattr(capture, "capture_pose", real)  # a resume captures nothing anyway
    pose_dir = _crash_state(data, final["resource"], "truncated", maps)
    assert (pose_dir / VERDICT).is_file()
    with TestClient(_app(data)) as c:
        assert c.get(final["resource"]).json()["status"] == "interrupted"
        job = c.post(f"{final['resource']}/resume").json()
        done = _wait_done(c, job["id"])
        assert done["status"] == "succeeded", done["error"]
        assert done["result"]["capture"]["captured"] == 0
        pose = c.get(final["resource"]).json()
        assert pose["status"] == "flagged"
        assert pose["error"] == "integrity check: camera or screen moved"
        c.app.state.services.maps_sync.drain()


TWO_CAMERAS = {"kind": "simulated", "screen": {"width_px": 320, "height_px": 240,
                                               "pitch_mm": [0.5, 0.5]},
               "cameras": [{"name": "left", "width": 64, "height": 48},
                           {"name": "right", "width": 72, "height": 54}]}


def test_a_camera_of_several_keeps_or_loses_its_pending_maps_as_a_pose_does(
        tmp_path: Path) -> None:
    """Each camera's maps of a several-camera pose are marked pending in the camera's
    folder and made durable in the background; after a crash intact ones are kept, and a
    damaged one makes the pose interrupted until a resume decodes the stored frames again."""
    data = tmp_path / "data"
    with TestClient(_app(data)) as c:
        rig = c.post("/rigs", json={"name": "two", "config": TWO_CAMERAS}).json()
        sess = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()
        final = _wait_done(c, c.post(f"/sessions/{sess['id']}/poses", json={}).json()["id"])
        assert final["status"] == "succeeded", final["error"]
        url = final["resource"]
        maps = {n: c.get(f"{url}/maps.npz", params={"camera": n}).content
                for n in ("left", "right")}
        c.app.state.services.maps_sync.drain()
    cameras = data / "poses" / url.rsplit("/", 1)[1] / "cameras"
    assert not list(cameras.glob(f"*/{PENDING}"))  # durable: every camera's mark is gone
    killed = _crash_maps(cameras / "left", "killed", maps["left"])
    lost = _crash_maps(cameras / "right", "truncated", maps["right"])
    with TestClient(_app(data)) as c:
        pose = c.get(url).json()
        assert pose["status"] == "interrupted" and "camera 'right'" in pose["error"]
        status = {cam["name"]: cam["status"] for cam in pose["cameras"]}
        assert status == {"left": "ready", "right": "interrupted"}
        assert not (killed / PENDING).exists()
        assert (killed / "maps.npz").read_bytes() == maps["left"]
        assert not (lost / PENDING).exists() and not (lost / "maps.npz").exists()
        job = c.post(f"{url}/resume").json()
        done = _wait_done(c, job["id"])
        assert done["status"] == "succeeded", done["error"]
        assert done["result"]["capture"]["captured"] == 0
        pose = c.get(url).json()
        assert pose["status"] == "ready"
        assert [cam["status"] for cam in pose["cameras"]] == ["ready", "ready"]
        again = load_maps(c.get(f"{url}/maps.npz", params={"camera": "right"}).content)
        c.app.state.services.maps_sync.drain()
    assert not list(cameras.glob(f"*/{PENDING}"))
    before = load_maps(maps["right"])
    for name in ("x", "y", "sigma_x", "sigma_y", "mask"):
        np.testing.assert_array_equal(getattr(again, name), getattr(before, name))
