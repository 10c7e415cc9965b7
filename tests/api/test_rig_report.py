"""The report of a rig calibration through the service: drawn by the job, it lists every
camera with its residuals and coverage, each camera's extrinsics with baseline and 1-sigma
matching the rig model, a verdict with thresholds, and links to every rig export."""

from __future__ import annotations

import re

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from hw_mocks.truth import SimulatorTruth
from tests.api.rig_report_checks import check_extrinsics_row, table_rows
from tests.api.test_rig_calibration_api import CONFIG, finished


@pytest.fixture(scope="module")
def rig_cal(tmp_path_factory: pytest.TempPathFactory):
    """A two-camera session of 5 poses, its rig calibration (one view held out)."""
    data = tmp_path_factory.mktemp("rigreport") / "data"
    with TestClient(create_app(ServiceConfig(data_dir=data, executor="threads"))) as c:
        rig = c.post("/rigs", json={"name": "pair", "config": CONFIG}).json()
        sess = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()
        pose_ids = []
        for pose in SimulatorTruth.from_config(CONFIG).screen_poses(5, seed=3):
            job = finished(c, c.post(f"/sessions/{sess['id']}/poses",
                                      json={"screen_pose": pose}).json()["id"])
            assert job["status"] == "succeeded", job["error"]
            pose_ids.append(job["resource"].rsplit("/", 1)[-1])
        r = c.post(f"/sessions/{sess['id']}/rig-calibrations",
                   json={"model": "opencv5", "heldout_pose_ids": pose_ids[-1:],
                         "options": {"max_points_per_view": 400}})
        assert r.status_code == 202, r.text
        job = finished(c, r.json()["id"])
        assert job["status"] == "succeeded", job["error"]
        yield c, job["resource"]


def test_rig_report_lists_every_camera_and_the_extrinsics_with_sigma(rig_cal) -> None:
    c, resource = rig_cal
    r = c.get(f"{resource}/report.html")
    assert r.status_code == 200, r.text
    page = r.text
    cams = table_rows(page, "cameras")
    assert [row[0] for row in cams] == ["left", "right"]
    for row in cams:
        assert row[1] == "opencv5" and row[2] == "96 x 72"
        assert float(row[3]) > 0  # fx
    rig = c.get(f"{resource}/rig").json()
    ext = rig["cameras"]["right"]["extrinsics"]
    row = check_extrinsics_row(page, "right", ext)
    # The simulated baseline is known from outside the product.
    _, t_true = SimulatorTruth.from_config(CONFIG).extrinsics("right")
    assert abs(float(row[1]) - np.linalg.norm(t_true)) < 5 * float(row[4]) + 0.05
    status = re.search(r'id="verdict" data-status="(\w+)"', page).group(1)
    assert status in ("pass", "warn", "fail")
    for name in ("left: coverage of its sensor", "right: whitened RMS in the joint fit",
                 "right: baseline 1-sigma", "right: rotation 1-sigma"):
        assert name in page
    links = re.findall(r'class="download" href="([^"]+)"', page)
    assert f"{resource}/rig" in links
    stereo = [h for h in links if "format=opencv-stereo" in h]
    assert stereo and c.get(stereo[0].replace("&amp;", "&")).status_code == 200
    assert any("camera=right" in h and "format=opencv-yaml" in h for h in links)
    png = re.findall(r'src="(report/coverage_\d\d\.png)"', page)
    assert len(png) == 2
    img = c.get(f"{resource.rsplit('/', 1)[0]}/{resource.rsplit('/', 1)[1]}/{png[0]}")
    assert img.status_code == 200 and img.content[:4] == b"\x89PNG"
