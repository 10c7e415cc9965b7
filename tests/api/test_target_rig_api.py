"""A rig calibrated over REST from board observations: one target session per camera, views
paired by shot name (POST /target-rig-calibrations), the rig model against the simulated
extrinsics and against `phasecal calibrate --observations` on the same files, an sGCC camera
in it, and the requests refused with a 422 naming the field."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.cli import main
from api.client import PhasecalClient
from api.config import ServiceConfig
from api.db import TargetRigCalibrationRecord
from calibration import rig_from_dict
from hw_mocks.cameras import mild_pinhole
from hw_mocks.rig_truth import RigTruth
from tests.api.test_rig_calibration_api import finished
from tests.calibration.rig.conftest import SCREEN, board_view_files, two_pinholes

VIEWS = 6
HELD = f"v{VIEWS - 1}"
RUNNING = "cal_00000000000000aa"


def _upload(c: TestClient, sid: str, path: str) -> str:
    r = c.post(f"/target-sessions/{sid}/views",
               files={"file": (Path(path).name, Path(path).read_bytes())})
    assert r.status_code == 201, r.text
    return r.json()["id"]


@pytest.fixture(scope="module")
def board_rig(tmp_path_factory: pytest.TempPathFactory):
    """Two simulated cameras' board observations (6 shots), each camera's views uploaded to
    its own target session: (client, body's cameras, CLI arguments, truth, folder)."""
    folder = tmp_path_factory.mktemp("target-rig")
    pair = two_pinholes()  # B with a larger sensor: each session has its own image size
    truth = RigTruth({**pair.cameras, "B": mild_pinhole(360, 270)}, pair.rotations,
                     pair.translations)
    args = board_view_files(folder, truth, SCREEN, VIEWS, np.random.default_rng(21))
    with TestClient(create_app(ServiceConfig(data_dir=folder / "data",
                                             executor="threads"))) as c:
        cameras: dict[str, dict] = {}
        for arg in args:
            name, path = arg.split("=", 1)
            cam, shot = name.split("/")
            if cam not in cameras:
                sid = c.post("/target-sessions", json={"name": cam, "target": "points"})
                cameras[cam] = {"session_id": sid.json()["id"], "views": {}}
            cameras[cam]["views"][shot] = _upload(c, cameras[cam]["session_id"], path)
        yield c, cameras, args, truth, folder


def _fit(c: TestClient, body: dict) -> tuple[dict, str]:
    r = c.post("/target-rig-calibrations", json=body)
    assert r.status_code == 202, r.text
    job = finished(c, r.json()["id"])
    return job, job["resource"]


def _z(rig_doc: dict, truth: RigTruth) -> np.ndarray:
    """B's pose relative to A against the truth over its predicted 1-sigma."""
    rig = rig_from_dict(rig_doc)
    r_true, t_true = truth.relative("A", "B")
    rot, t = rig.relative("A", "B")
    err = np.concatenate([cv2.Rodrigues(rot @ r_true.T)[0].ravel(), t - t_true])
    return err / np.sqrt(np.diag(rig.camera("B").covariance))


def test_board_rig_over_rest_matches_the_truth_and_the_cli(board_rig) -> None:
    c, cameras, args, truth, folder = board_rig
    job, resource = _fit(c, {"cameras": cameras, "model": "opencv5", "heldout_shots": [HELD]})
    assert job["status"] == "succeeded", job["error"]
    cal = c.get(resource).json()
    assert cal["status"] == "succeeded" and cal["reference"] == "A"
    sizes = {cam: c.get(f"/target-sessions/{spec['session_id']}/views").json()[0]["width"]
             for cam, spec in cameras.items()}
    assert sizes == {"A": 320, "B": 360}
    assert cal["stats"]["heldout"] and set(cal["stats"]["extrinsics"]) >= {"B"}
    doc = c.get(f"{resource}/rig").json()
    assert doc["format"] == "phasecal.rig/1"
    assert np.all(np.abs(_z(doc, truth)) < 3.0)
    out = folder / "cli-rig.json"
    assert main(["calibrate", "--observations", *args, "--model", "opencv5",
                 "--heldout-view", HELD, "-o", str(out)]) == 0
    cli = rig_from_dict(json.loads(out.read_text()))
    rest = rig_from_dict(doc)
    for a, b in zip(rest.relative("A", "B"), cli.relative("A", "B"), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)  # to rounding: sigma ~0.5 mm
    np.testing.assert_allclose(rest.camera("B").covariance, cli.camera("B").covariance,
                               rtol=1e-6)
    stereo = c.get(f"{resource}/rig/export", params={"format": "opencv-stereo",
                                                     "cameras": "A,B"})
    assert stereo.status_code == 200, stereo.text
    assert json.loads(stereo.headers["Phasecal-Export-Info"])
    one = c.get(f"{resource}/rig/export", params={"format": "opencv-yaml", "camera": "B"})
    assert one.status_code == 200 and b"camera_matrix" in one.content
    # the views it read can go; the calibration keeps its rig model
    view = cameras["B"]["views"][HELD]
    assert c.delete(f"/target-sessions/{cameras['B']['session_id']}/views/{view}"
                    ).status_code == 204
    assert c.get(f"{resource}/rig").status_code == 200
    cameras["B"]["views"][HELD] = _upload(c, cameras["B"]["session_id"],
                                          str(folder / f"B{VIEWS - 1}.npz"))
    assert c.delete(resource).status_code == 204
    assert c.get(resource).status_code == 404


def test_an_sgcc_camera_in_a_board_rig(board_rig) -> None:
    c, cameras, _, _, _ = board_rig
    job, resource = _fit(c, {"cameras": cameras, "model": "opencv5", "reference": "B",
                             "camera_models": {"A": "sgcc"}})
    assert job["status"] == "succeeded", job["error"]
    doc = c.get(f"{resource}/rig").json()
    assert doc["reference"] == "B"
    assert doc["cameras"]["A"]["model"]["type"] == "sgcc"
    assert "covariance_upper_f64_b64" in doc["cameras"]["A"]["model"]["params"]
    ros = c.get(f"{resource}/rig/export", params={"format": "ros-transforms"})
    assert ros.status_code == 200 and b"A" in ros.content


def _refusal(c: TestClient, body: dict) -> tuple[str, str]:
    r = c.post("/target-rig-calibrations", json={"model": "opencv5", **body})
    assert r.status_code == 422, r.text
    return r.json().get("field", ""), r.json()["detail"]


def test_rig_requests_the_fit_cannot_use_are_refused(board_rig) -> None:
    c, cameras, _, _, _ = board_rig
    a, b = cameras["A"], cameras["B"]
    field, detail = _refusal(c, {"cameras": {"A": a, "B": {**b, "session_id": "ses_nothere"}}})
    assert field == "cameras.B.session_id" and "does not exist" in detail
    field, detail = _refusal(c, {"cameras": {"A": a, "B": {**b, "session_id": a["session_id"]}}})
    assert field == "cameras.B.session_id" and "also camera A's" in detail
    wrong = {**b, "views": {**b["views"], "v0": a["views"]["v0"]}}
    field, detail = _refusal(c, {"cameras": {"A": a, "B": wrong}})
    assert field == "cameras.B.views.v0" and "is not a view of" in detail
    apart = {**b, "views": {f"b{k}": v for k, v in enumerate(b["views"].values())}}
    field, detail = _refusal(c, {"cameras": {"A": a, "B": apart}})
    assert field == "cameras" and "groups: A | B" in detail
    few = {**b, "views": dict(list(b["views"].items())[:2])}
    field, detail = _refusal(c, {"cameras": {"A": a, "B": few}})
    assert field == "cameras.B.views" and "needs >= 3 training views, got 2" in detail
    field, _ = _refusal(c, {"cameras": {"A": a, "B": b}, "heldout_shots": ["v9"]})
    assert field == "heldout_shots"
    field, _ = _refusal(c, {"cameras": {"A": a}})
    assert field == "cameras"
    field, _ = _refusal(c, {"cameras": {"A": a, "B": b}, "reference": "C"})
    assert field == "reference"
    field, _ = _refusal(c, {"cameras": {"A": a, "B": b}, "options": {"no_such": 1}})
    assert field == "options"
    field, detail = _refusal(c, {"cameras": {"A": a, "B": b}, "camera_models": {"B": "raygrid"}})
    assert field == "camera_models.B" and "dense decoded maps" in detail


def test_views_a_running_rig_calibration_reads_cannot_be_deleted(board_rig) -> None:
    c, cameras, _, _, _ = board_rig
    svc = c.app.state.services
    with svc.db.session() as s:  # a rig calibration whose job is running
        s.add(TargetRigCalibrationRecord(
            id=RUNNING, cameras=cameras, reference="A", status="running",
            camera_models={"A": "opencv5", "B": "opencv5"}, job_id="job_running"))
    sid, view = cameras["A"]["session_id"], cameras["A"]["views"]["v0"]
    r = c.delete(f"/target-sessions/{sid}/views/{view}")
    assert r.status_code == 409 and f"read by rig calibration {RUNNING}" in r.json()["detail"]
    assert c.delete(f"/target-sessions/{sid}").status_code == 409
    assert c.get(f"/target-sessions/{sid}/views/{view}/observations.npz").status_code == 200
    with svc.db.session() as s:
        s.get(TargetRigCalibrationRecord, RUNNING).status = "failed"
    assert c.delete(f"/target-rig-calibrations/{RUNNING}").status_code == 204


def test_the_python_client_calibrates_a_board_rig(board_rig, tmp_path) -> None:
    c, cameras, _, _, _ = board_rig

    def through_the_app(request: httpx.Request) -> httpx.Response:
        r = c.request(request.method, request.url.raw_path.decode(),
                      content=request.content, headers=dict(request.headers))
        return httpx.Response(r.status_code, headers=r.headers, content=r.content)

    with PhasecalClient("http://service", transport=httpx.MockTransport(through_the_app)
                        ) as client:
        job = client.calibrate_target_rig(cameras, "opencv5", heldout_shots=[HELD])
        assert finished(c, job["id"])["status"] == "succeeded"
        cal = client.get_target_rig_calibration(job["resource"].rsplit("/", 1)[1])
        assert cal["status"] == "succeeded" and cal["heldout_shots"] == [HELD]
        info = client.export_target_rig(cal, "opencv-stereo", tmp_path / "stereo.yaml",
                                        cameras="A,B")
        assert info and (tmp_path / "stereo.yaml").stat().st_size > 0
