"""REST exports and undistort-points of stored calibrations (in-process app)."""

from __future__ import annotations

import io
import json
import time

import cv2
import numpy as np
import pytest
import yaml
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from api.db import CalibrationRecord
from api.demo import demo_rig_config
from calibration.models.base import save_model
from calibration.models.parametric import OpenCV5Model, OpenCVRationalModel
from calibration.models.sgcc import SGCCModel, logmap

K = np.array([[150.0, 0, 80.5], [0, 151.0, 60.25], [0, 0, 1]])
DIST = [-0.2, 0.05, 1e-3, -5e-4, 0.01, 0.02, 0.0, 0.0, 1e-3, 0.0, -1e-3, 0.0]


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory):
    """(client, {name: calibration id}) with stored rational, opencv5 and sgcc models."""
    cfg = ServiceConfig(data_dir=tmp_path_factory.mktemp("exports") / "data")
    app = create_app(cfg)
    with TestClient(app) as c:
        rig = c.post("/rigs", json={"name": "r", "config": demo_rig_config(160, 120)}).json()
        ses = c.post("/sessions", json={"name": "s", "rig_id": rig["id"]}).json()
        svc = app.state.services
        rational = OpenCVRationalModel((160, 120), K, DIST)
        opencv5 = OpenCV5Model((160, 120), K, DIST[:5])
        sg = SGCCModel((160, 120), (4, 4))
        uu, vv = np.meshgrid(np.linspace(-0.5, 159.5, 60), np.linspace(-0.5, 119.5, 45))
        _, d = opencv5.unproject(np.stack([uu.ravel(), vv.ravel()], axis=1))
        sg.set_params(sg.grid.fit(uu.ravel(), vv.ravel(), logmap(d), smooth=1e-12).ravel())
        models = {"rational": rational, "opencv5": opencv5, "sgcc": sg}
        ids = {}
        for i, (name, model) in enumerate(models.items()):
            cid = f"cal_{i:016x}"
            save_model(model, svc.store.dir_for(cid) / "model.json")
            with svc.db.session() as s:
                s.add(CalibrationRecord(id=cid, session_id=ses["id"], model=model.type_name,
                                        pose_ids=[], status="succeeded", exports=["model.json"],
                                        created_at=time.time()))
            ids[name] = cid
        yield c, ids


def test_opencv_yaml_ros_mrcal(api):
    c, ids = api
    r = c.get(f"/calibrations/{ids['rational']}/export", params={"format": "opencv-yaml"})
    assert r.status_code == 200 and "attachment" in r.headers["content-disposition"]
    fs = cv2.FileStorage(r.text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    np.testing.assert_array_equal(fs.getNode("distortion_coefficients").mat().ravel(), DIST)
    r = c.get(f"/calibrations/{ids['rational']}/export", params={"format": "ros"})
    assert r.status_code == 422
    assert r.headers["content-type"] == "application/problem+json"
    assert "thin-prism" in r.json()["detail"]
    r = c.get(f"/calibrations/{ids['opencv5']}/export",
              params={"format": "ros", "camera_name": "left"})
    assert yaml.safe_load(r.text)["camera_name"] == "left"
    r = c.get(f"/calibrations/{ids['rational']}/export", params={"format": "mrcal"})
    assert "LENSMODEL_OPENCV12" in r.text
    assert json.loads(r.headers["phasecal-export-info"])["exact"] is True


def test_generic_remap_opencv_fit_and_spline(api):
    c, ids = api
    sg = ids["sgcc"]
    r = c.get(f"/calibrations/{sg}/export", params={"format": "opencv-yaml"})
    assert r.status_code == 422 and "no camera_matrix" in r.json()["detail"]
    r = c.get(f"/calibrations/{sg}/export", params={"format": "remap"})
    assert r.status_code == 422 and "pinhole" in r.json()["detail"]
    r = c.get(f"/calibrations/{sg}/export",
              params={"format": "remap", "pinhole": "100,100,79.5,59.5,160,120"})
    maps = np.load(io.BytesIO(r.content))
    assert maps["map_x"].shape == (120, 160) and maps["map_x"].dtype == np.float32
    r = c.get(f"/calibrations/{sg}/export", params={"format": "remap", "pinhole": "1,2"})
    assert r.status_code == 422 and "FX,FY,CX,CY,W,H" in r.json()["detail"]
    r = c.get(f"/calibrations/{sg}/export", params={"format": "opencv-fit",
                                                    "opencv_kind": "opencv5"})
    npz = np.load(io.BytesIO(r.content))
    assert npz["residual_px"].shape == (120, 160)
    info = json.loads(r.headers["phasecal-export-info"])
    assert info["residual"]["rms_px"] >= 0
    r = c.get(f"/calibrations/{sg}/export", params={"format": "mrcal"})
    assert "LENSMODEL_SPLINED_STEREOGRAPHIC" in r.text
    assert json.loads(r.headers["phasecal-export-info"])["residual"]["rms_px"] < 0.01
    r = c.get(f"/calibrations/{sg}/export", params={"format": "nope"})
    assert r.status_code == 422


def test_undistort_points(api):
    c, ids = api
    pix = [[10.0, 20.0], [80.5, 60.25], [150.0, 100.0]]
    r = c.post(f"/calibrations/{ids['opencv5']}/undistort-points", json={"pixels": pix})
    assert r.status_code == 200
    ref = cv2.undistortPoints(np.array(pix).reshape(-1, 1, 2), K, np.array(DIST[:5]), R=None,
                              P=K, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                             200, 1e-15))
    assert np.max(np.abs(np.array(r.json()["pixels"]) - ref[:, 0, :])) < 1e-6
    r = c.post(f"/calibrations/{ids['sgcc']}/undistort-points", json={"pixels": pix})
    assert r.status_code == 422 and "pinhole" in r.json()["detail"]
    r = c.post(f"/calibrations/{ids['sgcc']}/undistort-points",
               json={"pixels": pix, "pinhole": [100, 100, 79.5, 59.5],
                     "align_to": ids["opencv5"]})
    assert r.status_code == 200 and len(r.json()["pixels"]) == 3
