"""Quick intrinsics over REST: a session's imported poses -> white flats / maps -> K, vs truth."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from acquisition.patterns import build_plan
from api.client import PhasecalClient
from hw_mocks.cameras import PinholeCamera
from hw_mocks.optics import OpticalSetup
from hw_mocks.rectangles import whole_screen_poses
from hw_mocks.rig import DEFAULT_SCREEN
from hw_mocks.sensor import SensorModel
from hw_mocks.synthetic import render_plan_frames
from tests.api_server import ServerProcess

CAM = PinholeCamera(320, 240, fx=260.0, fy=260.0, cx=165.5, cy=116.0)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):
    srv = ServerProcess(tmp_path_factory.mktemp("intr") / "data")
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def client(server: ServerProcess):
    c = PhasecalClient(server.url)
    yield c
    c.close()


@pytest.fixture(scope="module")
def session(client: PhasecalClient, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A session with four imported poses of the simulated screen, whole screen in view."""
    plan = build_plan(DEFAULT_SCREEN.width_px, DEFAULT_SCREEN.height_px, 0.25, preset="fast")
    rng = np.random.default_rng(41)
    d = tmp_path_factory.mktemp("frames")
    ses = client.post("/sessions", {"name": "quick", "plan": plan.to_dict()})
    jobs = []
    for i, pose in enumerate(whole_screen_poses(CAM, DEFAULT_SCREEN, 4, rng)):
        setup = OpticalSetup(CAM, pose, DEFAULT_SCREEN, blur_sigma_screen_px=0.5,
                             ambient=2e3, supersample=2)
        frames, _ = render_plan_frames(plan, setup, SensorModel(), exposure_s=0.04, rng=rng)
        np.save(d / f"pose{i}.npy", frames)
        jobs.append(client.import_frames(ses["id"], [d / f"pose{i}.npy"]))
    ses["decode_jobs"] = jobs
    return ses


def _err(r: dict) -> float:
    return max(abs(r["fx"] / CAM.fx - 1), abs(r["fy"] / CAM.fy - 1),
               abs(r["cx"] - CAM.cx) / CAM.fx, abs(r["cy"] - CAM.cy) / CAM.fx)


def test_quick_intrinsics_from_white_flats_then_maps(client: PhasecalClient,
                                                     session: dict) -> None:
    sid, c = session["id"], client
    # white flats: no need to wait for decoding
    job = c.post(f"/sessions/{sid}/intrinsics", {"method": "rectangle",
                                                 "square_pixels": True})
    assert job["kind"] == "intrinsics"
    final = c.wait(job, timeout_s=120)
    assert final["status"] == "succeeded", final["error"]
    res = final["result"]
    assert res["method"] == "rectangle-square" and len(res["pose_ids"]) == 4
    assert _err(res) < 0.02 and res["std"]["fx"] > 0
    assert c.get_intrinsics(sid)["fx"] == res["fx"]
    for j in session["decode_jobs"]:
        assert c.wait(j, timeout_s=300)["status"] == "succeeded"
    final = c.wait(c.post(f"/sessions/{sid}/intrinsics",
                          {"method": "rectangle", "source": "maps"}), timeout_s=120)
    assert final["status"] == "succeeded", final["error"]
    assert final["result"]["source"] == "maps" and _err(final["result"]) < 0.01


def test_quick_intrinsics_bad_requests(server: ServerProcess, client: PhasecalClient,
                                       session: dict) -> None:
    sid = session["id"]
    url = f"{server.url}/sessions/{sid}/intrinsics"
    with httpx.Client() as h:
        r = h.post(url, json={"method": "vanishing"})
        assert r.status_code == 422 and r.headers["content-type"] == "application/problem+json"
        r = h.post(url, json={"method": "rectangle", "pose_ids": ["pose_0123456789abcdef"]})
        assert r.status_code == 422 and "not a pose of session" in r.json()["detail"]
        two = [p["id"] for p in client.get(f"/sessions/{sid}/poses")][:2]
        r = h.post(url, json={"method": "rectangle", "pose_ids": two})
        assert r.status_code == 409 and "needs >= 4" in r.json()["detail"]
    # selfcal needs two rectangles per image: the job fails with a specific reason
    final = client.wait(client.quick_intrinsics(sid, "selfcal"), timeout_s=120, check=False)
    assert final["status"] == "failed" and "expected 2" in final["error"]


def test_no_result_yet_is_404(server: ServerProcess, client: PhasecalClient) -> None:
    sid = client.post("/sessions", {"name": "empty"})["id"]
    r = httpx.get(f"{server.url}/sessions/{sid}/intrinsics")
    assert r.status_code == 404 and "no intrinsics yet" in r.json()["detail"]


def test_white_flat_not_yet_captured_is_409(server: ServerProcess, client: PhasecalClient,
                                            session: dict) -> None:
    """A captured pose whose store has not marked the white flat done is not read as one."""
    from calibration.fit.classic.quick import white_flat_index

    sid = session["id"]
    pose = client.get(f"/sessions/{sid}/poses")[0]
    plan = build_plan(DEFAULT_SCREEN.width_px, DEFAULT_SCREEN.height_px, 0.25, preset="fast")
    folder = server.data_dir / "poses" / pose["id"]
    done = np.ones(len(plan.frames), dtype=np.uint8)
    done[white_flat_index(plan)] = 0  # as if the capture stopped before the flat
    (folder / "frames.done").write_bytes(done.tobytes())
    try:
        r = httpx.post(f"{server.url}/sessions/{sid}/intrinsics",
                       json={"method": "rectangle", "square_pixels": True})
        assert r.status_code == 409 and "white flat" in r.json()["detail"]
        assert pose["id"] in r.json()["detail"]
    finally:
        (folder / "frames.done").unlink()
