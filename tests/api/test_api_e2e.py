"""End to end over HTTP against a real uvicorn subprocess: import, decode, bad input, jobs.

The whole-session flow on the simulated rig (capture, calibrate, cancel, restart) is in
`test_api_session.py`; this file covers what needs only the decoder.
"""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from acquisition.patterns import build_plan
from api.client import PhasecalClient
from calibration.shared.maps import load_maps
from calibration.shared.plan import CosineFrame, FlatFrame, Plan
from tests.api_server import ServerProcess

H, W = 120, 160
MAX_UPLOAD = 2_000_000


def affine_truth() -> tuple[np.ndarray, np.ndarray]:
    """Screen px seen by each camera pixel of a simple affine test camera."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return 30.0 + 1.2 * u + 0.05 * v, 20.0 + 1.1 * v - 0.03 * u


def render(plan: Plan, rng: np.random.Generator, noise_dn: float = 1.0) -> np.ndarray:
    """(F, H, W) uint8 frames of the plan through the affine camera (docs/formats.md, the
    pattern plan)."""
    x, y = affine_truth()
    frames = []
    for f in plan.frames:
        if isinstance(f, FlatFrame):
            lin = np.full((H, W), f.level)
        else:
            assert isinstance(f, CosineFrame)
            c = x if f.axis == "x" else y
            lin = f.offset + f.amplitude * np.cos(2 * math.pi * c / f.period_px + f.phase_shift)
        img = 15.0 + 220.0 * lin + rng.normal(0.0, noise_dn, (H, W))
        frames.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return np.stack(frames)


@pytest.fixture(scope="module")
def plan() -> Plan:
    return build_plan(256, 192, 0.5, preset="fast")


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):
    srv = ServerProcess(tmp_path_factory.mktemp("e2e") / "data",
                        env={"PHASECAL_MAX_UPLOAD_BYTES": str(MAX_UPLOAD)})
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def client(server: ServerProcess):
    c = PhasecalClient(server.url)
    yield c
    c.close()


@pytest.fixture(scope="module")
def session(client: PhasecalClient, plan: Plan) -> dict:
    return client.post("/sessions", {"name": "e2e", "plan": plan.to_dict()})


def _npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def _check_maps(maps_bytes: bytes) -> None:
    maps = load_maps(maps_bytes)
    x_true, y_true = affine_truth()
    assert maps.valid_count() > 0.9 * H * W
    m = maps.mask
    ex, ey = maps.x[m] - x_true[m], maps.y[m] - y_true[m]
    # accurate against ground truth AND consistent with the predicted uncertainty
    assert np.median(np.abs(ex)) < 0.2 and np.median(np.abs(ey)) < 0.2
    zx = ex / maps.sigma_x[m]
    assert 0.3 < np.std(zx) < 3.0


def test_import_npy_decodes_to_truth(client: PhasecalClient, session: dict, plan: Plan,
                                     tmp_path: Path) -> None:
    frames = render(plan, np.random.default_rng(1))
    path = tmp_path / "frames.npy"
    np.save(path, frames)
    job = client.import_frames(session["id"], [path])
    assert job["kind"] == "decode" and job["status"] in ("queued", "running", "succeeded")
    final = client.wait(job, timeout_s=120)
    assert final["status"] == "succeeded", final["error"]
    pose_url = final["resource"]
    pose = client.get(pose_url)
    assert (pose["status"], pose["width"], pose["height"]) == ("ready", W, H)
    _check_maps(client.request("GET", f"{pose_url}/maps.npz").content)
    for kind in ("x", "y", "sigma", "mask"):
        r = client.request("GET", f"{pose_url}/preview/{kind}.png")
        img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
        # the map drawn with its axes and colour bar: larger than the map itself
        assert r.headers["content-type"] == "image/png" and img.shape[1] > W and img.std() > 0


def test_import_png_folder(client: PhasecalClient, session: dict, plan: Plan,
                           tmp_path: Path) -> None:
    frames = render(plan, np.random.default_rng(2))
    paths = []
    for i, img in enumerate(frames):
        p = tmp_path / f"frame_{i:04d}.png"
        cv2.imwrite(str(p), img)
        paths.append(p)
    final = client.wait(client.import_frames(session["id"], paths[::-1]), timeout_s=120)
    assert final["status"] == "succeeded", final["error"]
    _check_maps(client.request("GET", f"{final['resource']}/maps.npz").content)


def _problem(r: httpx.Response, status: int, slug: str | None = None) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == "application/problem+json"
    body = r.json()
    assert body["status"] == status and body["detail"]
    if slug:
        assert body["type"].endswith("/" + slug), body
    return body


def test_bad_uploads_are_problems(server: ServerProcess, session: dict, plan: Plan) -> None:
    url = f"{server.url}/sessions/{session['id']}/poses/import"
    frames = render(plan, np.random.default_rng(3))
    with httpx.Client(timeout=60) as h:
        body = _problem(h.post(url, files={"files": ("f.npy", _npy_bytes(frames[:-1]))}), 422,
                        "frames-plan-mismatch")
        assert f"plan has {len(plan.frames)}" in body["detail"]
        _problem(h.post(url, files={"files": ("f.npy", b"\x93NUMPY garbage")}), 422,
                 "invalid-frames")
        _problem(h.post(url, files={"files": ("f.npy", _npy_bytes(frames[0]))}), 422,
                 "invalid-frames")
        wide = _npy_bytes(frames[:, :9].astype(np.int64))
        _problem(h.post(url, files={"files": ("f.npy", wide)}), 422, "invalid-frames")
        pngs = [("files", (f"img{i}.png", cv2.imencode(".png", f)[1].tobytes()))
                for i, f in enumerate(frames)]
        _problem(h.post(url, files=pngs), 422, "invalid-frames")
        colour = [("files", (f"frame_{i:04d}.png",
                             cv2.imencode(".png", np.dstack([f, f, f]))[1].tobytes()))
                  for i, f in enumerate(frames)]
        _problem(h.post(url, files=colour), 422, "invalid-frames")
        _problem(h.post(url, json={"files": []}), 422, "validation-error")
        big = np.zeros((len(plan.frames), 320, 320), np.uint8)
        _problem(h.post(url, files={"files": ("f.npy", _npy_bytes(big))}), 413, "too-large")
        _problem(h.post(f"{server.url}/sessions/ses_0000000000000000/poses/import",
                        files={"files": ("f.npy", _npy_bytes(frames))}), 404, "not-found")
        maps_url = f"{server.url}/sessions/{session['id']}/poses/import-maps"
        _problem(h.post(maps_url, files={"file": ("m.npz", b"PK\x03\x04 not a zip")}), 422,
                 "invalid-maps")
    # none of the rejected uploads left a pose or a stray file behind
    poses = httpx.get(f"{server.url}/sessions/{session['id']}/poses").json()
    assert all(p["status"] == "ready" for p in poses)
    assert not any((server.data_dir / "tmp").iterdir())


def test_unknown_ids_and_wrong_types(server: ServerProcess, session: dict) -> None:
    with httpx.Client(base_url=server.url, timeout=30) as h:
        for path in ("/sessions/ses_0000000000000000", "/jobs/job_0000000000000000",
                     "/calibrations/cal_0000000000000000", "/rigs/rig_0000000000000000",
                     f"/sessions/{session['id']}/poses/pose_0000000000000000",
                     "/sessions/..%2F..%2Fetc%2Fpasswd", "/calibrations/cal_x/files/model.json"):
            _problem(h.get(path), 404)
        _problem(h.post("/sessions", content=b"{", headers={"content-type": "application/json"}),
                 422)
        _problem(h.post("/sessions", content=b"a=b",
                        headers={"content-type": "application/x-www-form-urlencoded"}), 422)
        _problem(h.post(f"/sessions/{session['id']}/calibrations", json={"model": "nope"}), 422)
        _problem(h.post(f"/sessions/{session['id']}/calibrations",
                        json={"model": "opencv5", "pose_ids": ["pose_0000000000000000"]}), 422)
        _problem(h.delete("/sessions"), 405)
        bad_plan = {"format": "phasecal.plan/1", "screen": {"width_px": 10}, "frames": []}
        body = _problem(h.post("/sessions", json={"plan": bad_plan}), 422, "invalid-plan")
        assert "screen.height_px" in body["detail"]


def test_jobs_listing_filters_and_sse(client: PhasecalClient, server: ServerProcess,
                                      session: dict, plan: Plan, tmp_path: Path) -> None:
    path = tmp_path / "frames.npy"
    np.save(path, render(plan, np.random.default_rng(4)))
    # Three decode jobs of its own (tests of this module may run on other xdist workers).
    for _ in range(2):
        client.import_frames(session["id"], [path])
    job = client.import_frames(session["id"], [path])
    events = []
    with httpx.stream("GET", f"{server.url}/jobs/{job['id']}/events", timeout=120) as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        name = None
        for line in r.iter_lines():
            if line.startswith("event: "):
                name = line[7:]
            elif line.startswith("data: "):
                events.append((name, json.loads(line[6:])))
                if name == "end":
                    break
    assert events[-1][0] == "end" and events[-1][1]["status"] == "succeeded"
    assert all(e[1]["id"] == job["id"] for e in events)
    page = client.get("/jobs", kind="decode", session_id=session["id"], limit=2)
    assert page["total"] >= 3 and len(page["items"]) == 2
    page2 = client.get("/jobs", kind="decode", session_id=session["id"], limit=2, offset=2)
    ids = {j["id"] for j in page["items"]} | {j["id"] for j in page2["items"]}
    assert len(ids) == len(page["items"]) + len(page2["items"])
    assert client.get("/jobs", status="failed", session_id=session["id"])["total"] == 0
    with pytest.raises(Exception, match="409"):
        client.post(f"/jobs/{job['id']}/cancel")
