"""Uploads are validated before anything is stored; poses, calibrations and sessions can be
deleted (records and files), except while a job uses them."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from acquisition.patterns import build_plan
from api.app import create_app
from api.config import ServiceConfig
from hw_mocks.cameras import mild_pinhole
from hw_mocks.poses import random_poses
from hw_mocks.synthetic import synthetic_maps
from tests.api.test_api_units import FnJob

PLAN = build_plan(640, 480, 0.5, preset="fast")
W, H = 64, 48


def good_maps(seed: int = 0, size: tuple[int, int] = (W, H)):
    cam = mild_pinhole(*size)
    rng = np.random.default_rng(seed)
    pose = random_poses(cam, PLAN.screen, 1, rng)[0]
    maps, _ = synthetic_maps(cam, pose, PLAN.screen, sigma_px=0.05, rng=rng)
    maps.meta["plan_digest"] = PLAN.digest()
    return maps


def npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def arrays(maps) -> dict:
    return {k: v for k, v in np.load(io.BytesIO(maps.to_npz_bytes())).items()}


@pytest.fixture()
def env(tmp_path: Path):
    app = create_app(ServiceConfig(data_dir=tmp_path / "data", executor="threads",
                                   max_upload_bytes=1 << 20))
    with TestClient(app) as c:
        sess = c.post("/sessions", json={"plan": PLAN.to_dict()}).json()
        yield c, sess["id"], tmp_path / "data", app.state.services


def _import(c: TestClient, sid: str, data: bytes, name: str = "maps.npz"):
    return c.post(f"/sessions/{sid}/poses/import-maps", files={"file": (name, data)})


def test_bad_maps_are_refused_before_storing(env) -> None:
    c, sid, data_dir, _ = env
    a = arrays(good_maps())
    n = a["x"].size
    cases = {
        "0x0": ({**{k: np.zeros((0, 0), v.dtype) for k, v in a.items() if k != "meta"},
                 "meta": a["meta"]}, "non-empty 2-D"),
        "all-NaN": ({**a, "x": np.full((H, W), np.nan), "mask": np.ones((H, W), bool)}, "x:"),
        "negative sigma": ({**a, "sigma_x": -a["sigma_x"]}, "sigma_x:"),
        "infinite sigma": ({**a, "sigma_y": np.full((H, W), np.inf, np.float32)}, "sigma_y:"),
        "huge coordinates": ({**a, "y": np.where(a["mask"], 1e300, np.nan)}, "y:"),
        "wrong dtype": ({**a, "x": a["x"].astype(np.float32)}, "x: dtype float32"),
        "shapes disagree": ({**a, "sigma_x": a["sigma_x"][:-1]}, "sigma_x: shape"),
        "no valid pixel": ({**a, "mask": np.zeros((H, W), bool)}, "mask: no valid pixel"),
        "extra member": ({**a, "evil": np.zeros(3)}, "unexpected member"),
    }
    for label, (arrs, needle) in cases.items():
        r = _import(c, sid, npz(**arrs), f"{label}.npz")
        assert r.status_code == 422, (label, r.text)
        assert r.json()["detail"].startswith(f"{label}.npz:"), r.json()
        if needle:
            assert needle in r.json()["detail"], (label, r.json()["detail"])
    assert n > 0 and c.get(f"/sessions/{sid}/poses").json() == []
    assert list((data_dir / "poses").glob("*/maps.npz")) == []
    r = _import(c, sid, good_maps().to_npz_bytes())
    assert r.status_code == 201, r.text
    other = arrays(good_maps())
    small = {k: (v[:-2, :-2] if v.ndim == 2 else v) for k, v in other.items()}
    r = _import(c, sid, npz(**small), "smaller.npz")
    assert r.status_code == 422 and "session's camera is 64x48" in r.json()["detail"]


def test_zip_bomb_is_refused_from_its_declared_sizes(env) -> None:
    c, sid, _, _ = env
    big = 600
    bomb = npz(x=np.zeros((big, big)), y=np.zeros((big, big)),
               sigma_x=np.zeros((big, big), np.float32), sigma_y=np.zeros((big, big), np.float32),
               mask=np.zeros((big, big), bool), modulation_x=np.zeros((big, big), np.float32),
               modulation_y=np.zeros((big, big), np.float32), meta=np.array("{}"))
    assert len(bomb) < 100_000  # 10 MB of arrays compress to a few kB
    r = _import(c, sid, bomb, "bomb.npz")
    assert r.status_code == 413 and "expands to" in r.json()["detail"]
    # a header declaring more data than its member holds (numpy would allocate it first)
    a = arrays(good_maps())
    raw = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        raw, {"descr": "<f8", "fortran_order": False, "shape": (H * 1000, W)})
    raw.write(a["x"].tobytes())
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("x.npy", raw.getvalue())
        for k, v in a.items():
            if k != "x":
                one = io.BytesIO()
                np.save(one, v)
                zf.writestr(f"{k}.npy", one.getvalue())
    r = _import(c, sid, buf.getvalue(), "lying.npz")
    assert r.status_code == 422 and "more than the member holds" in r.json()["detail"]


def _png(img: np.ndarray) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


def test_frame_uploads_name_the_bad_file(env) -> None:
    c, sid, _, _ = env
    n = len(PLAN.frames)
    frames = [(f"frame_{i:04d}.png", _png(np.full((H, W), 100, np.uint8))) for i in range(n)]
    for label, bad, needle in (("empty", b"", "empty file"),
                               ("16-bit", _png(np.full((H, W), 100, np.uint16)), "uint16"),
                               ("size", _png(np.full((H + 2, W), 100, np.uint8)), "shape")):
        files = list(frames)
        files[3] = ("frame_0003.png", bad)
        r = c.post(f"/sessions/{sid}/poses/import",
                   files=[("files", (name, data, "image/png")) for name, data in files])
        assert r.status_code == 422, (label, r.text)
        assert r.json()["detail"].startswith("frame_0003.png:") and needle in r.json()["detail"]


def test_delete_pose_calibration_session(env) -> None:
    c, sid, data_dir, svc = env
    poses = [_import(c, sid, good_maps(k).to_npz_bytes()).json()["id"] for k in range(3)]
    assert (data_dir / "poses" / poses[0] / "maps.npz").exists()
    # a job holding a pose: DELETE answers 409 and removes nothing
    with svc.db.claim_session() as s:
        holder = FnJob(session_id=sid, claims=(poses[1],))
        job = svc.jobs.create(s, holder)
    r = c.delete(f"/sessions/{sid}/poses/{poses[1]}")
    assert r.status_code == 409 and job.id in r.json()["detail"]
    assert c.delete(f"/sessions/{sid}").status_code == 409
    assert (data_dir / "poses" / poses[1] / "maps.npz").exists()
    assert c.delete(f"/sessions/{sid}/poses/{poses[0]}").status_code == 204
    assert not (data_dir / "poses" / poses[0]).exists()
    assert c.get(f"/sessions/{sid}/poses/{poses[0]}").status_code == 404
    assert c.delete(f"/sessions/{sid}/poses/{poses[0]}").status_code == 404
    nxt = _import(c, sid, good_maps(5).to_npz_bytes()).json()
    assert nxt["index"] == 3  # indices stay unique after a delete
    svc.jobs.cancel(job.id)
    with svc.db.session() as s:  # end the never-started job as its driver would
        svc.jobs._finish(job.id, holder, "cancelled", "test")
    assert c.delete("/calibrations/cal_0123456789abcdef").status_code == 404
    job = c.post(f"/sessions/{sid}/calibrations", json={  # 3 poses: the model's minimum
        "model": "opencv5", "pose_ids": [poses[1], poses[2], nxt["id"]]})
    assert job.status_code == 202, job.text
    final = job.json()
    while final["status"] in ("queued", "running"):
        final = c.get(f"/jobs/{final['id']}").json()
    cal_id = final["resource"].rsplit("/", 1)[-1]
    assert (data_dir / "calibrations" / cal_id).is_dir()
    assert c.delete(f"/calibrations/{cal_id}").status_code == 204
    assert not (data_dir / "calibrations" / cal_id).exists()
    assert c.get(f"/calibrations/{cal_id}").status_code == 404
    assert c.delete(f"/sessions/{sid}").status_code == 204
    assert c.get(f"/sessions/{sid}").status_code == 404
    assert not (data_dir / "sessions" / sid).exists()
    assert not any((data_dir / "poses" / p).exists() for p in poses)
