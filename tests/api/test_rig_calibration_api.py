"""A rig calibration through the service: poses captured on two simulated cameras, fitted
jointly (POST /sessions/{id}/rig-calibrations), the rig model and its exports over REST,
checked against the simulator's extrinsics; bad requests are 4xx naming the field."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from hw_mocks.truth import SimulatorTruth

CONFIG = {"kind": "simulated", "screen": {"width_px": 320, "height_px": 240,
                                          "pitch_mm": [0.5, 0.5]},
          "cameras": [{"name": "left", "model": "mild_pinhole", "width": 96, "height": 72},
                      {"name": "right", "model": "mild_pinhole", "width": 96, "height": 72}]}
POSES = 5


def finished(c: TestClient, job_id: str, timeout_s: float = 600) -> dict:
    """The job's final state (the rig tests' one waiting loop)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = c.get(f"/jobs/{job_id}").json()
        if job["status"] not in ("queued", "running"):
            return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not finish")


@pytest.fixture(scope="module")
def rig_session(tmp_path_factory: pytest.TempPathFactory):
    """A session of 5 poses on a two-camera simulated rig, and its rig calibration."""
    data = tmp_path_factory.mktemp("rigcal") / "data"
    with TestClient(create_app(ServiceConfig(data_dir=data, executor="threads"))) as c:
        rig = c.post("/rigs", json={"name": "pair", "config": CONFIG}).json()
        sess = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()
        for pose in SimulatorTruth.from_config(CONFIG).screen_poses(POSES, seed=3):
            job = finished(c, c.post(f"/sessions/{sess['id']}/poses",
                                      json={"screen_pose": pose}).json()["id"])
            assert job["status"] == "succeeded", job["error"]
        r = c.post(f"/sessions/{sess['id']}/rig-calibrations",
                   json={"model": "opencv5", "options": {"max_points_per_view": 500}})
        assert r.status_code == 202, r.text
        job = finished(c, r.json()["id"])
        assert job["status"] == "succeeded", job["error"]
        yield c, sess["id"], job["resource"]


def test_rig_model_over_rest_matches_the_simulated_extrinsics(rig_session) -> None:
    c, _, resource = rig_session
    cal = c.get(resource).json()
    assert cal["status"] == "succeeded" and "rig.json" in cal["exports"]
    rig = c.get(f"{resource}/rig").json()
    assert rig["format"] == "phasecal.rig/1" and rig["reference"] == "left"
    ext = rig["cameras"]["right"]["extrinsics"]
    r_true, t_true = SimulatorTruth.from_config(CONFIG).extrinsics("right")
    sigma = np.sqrt(np.diag(ext["covariance"]))
    rot_err = cv2.Rodrigues(np.asarray(ext["R"]) @ r_true.T)[0].ravel()
    t_err = np.asarray(ext["t_mm"]) - t_true
    assert np.all(np.abs(np.concatenate([rot_err, t_err]) / sigma) < 5), (rot_err, t_err, sigma)
    stereo = c.get(f"{resource}/rig/export", params={"format": "opencv-stereo",
                                                     "cameras": "left,right"})
    assert stereo.status_code == 200 and b"K2" in stereo.content
    mrcal = c.get(f"{resource}/rig/export", params={"format": "mrcal", "camera": "right"})
    assert mrcal.status_code == 200 and b"rig's reference frame" in mrcal.content


def test_bad_rig_requests_name_the_field(rig_session) -> None:
    c, sid, resource = rig_session
    for body, field in (({"model": "opencv5", "camera_models": {"back": "fisheye"}},
                         "camera_models"),
                        ({"model": "opencv5", "reference": "back"}, "reference"),
                        ({"model": "opencv5", "options": {"outlier_sigmas": 1.0}}, "options")):
        r = c.post(f"/sessions/{sid}/rig-calibrations", json=body)
        assert r.status_code == 422 and r.json()["field"] == field, r.text
    r = c.get(f"{resource}/rig/export", params={"format": "ros"})
    assert r.status_code == 422 and "name one (--camera)" in r.json()["detail"]
