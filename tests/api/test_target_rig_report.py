"""The report of a rig calibrated over REST from board observations: drawn by the job, it
names every camera with its coverage from the detected points, each camera's extrinsics with
1-sigma matching the rig model, the held-out shots and links to this rig's own exports; a
calibration that is running, failed or unknown has no report."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.config import ServiceConfig
from api.db import TargetRigCalibrationRecord
from calibration import ReportHeader, RigReportInputs
from calibration.shared.observations import load_observations
from tests.api.rig_report_checks import check_extrinsics_row, table_rows
from tests.api.test_rig_calibration_api import finished
from tests.calibration.rig.conftest import SCREEN, board_view_files, two_pinholes

VIEWS = 5
HELD = f"v{VIEWS - 1}"
COVERAGE_CELLS = (16, 12)  # the report's grid of each sensor (nx, ny)


@pytest.fixture(scope="module")
def board_report(tmp_path_factory: pytest.TempPathFactory):
    """Two simulated cameras' board views in one target session each, and their rig
    calibration (one shot held out): (client, resource, cameras, observation files)."""
    folder = tmp_path_factory.mktemp("target-rig-report")
    args = board_view_files(folder, two_pinholes(), SCREEN, VIEWS, np.random.default_rng(5))
    with TestClient(create_app(ServiceConfig(data_dir=folder / "data",
                                             executor="threads"))) as c:
        cameras: dict[str, dict] = {}
        files: dict[str, dict[str, str]] = {}
        for arg in args:
            name, path = arg.split("=", 1)
            cam, shot = name.split("/")
            if cam not in cameras:
                sid = c.post("/target-sessions", json={"name": cam, "target": "points"})
                cameras[cam] = {"session_id": sid.json()["id"], "views": {}}
            r = c.post(f"/target-sessions/{cameras[cam]['session_id']}/views",
                       files={"file": (Path(path).name, Path(path).read_bytes())})
            assert r.status_code == 201, r.text
            cameras[cam]["views"][shot] = r.json()["id"]
            files.setdefault(cam, {})[shot] = path
        r = c.post("/target-rig-calibrations", json={
            "cameras": cameras, "model": "opencv5", "heldout_shots": [HELD]})
        assert r.status_code == 202, r.text
        job = finished(c, r.json()["id"])
        assert job["status"] == "succeeded", job["error"]
        yield c, job["resource"], cameras, files


def _covered_fraction(paths: list[str]) -> float:
    """The fraction of a 320 x 240 sensor's coverage cells holding a detected point."""
    nx, ny = COVERAGE_CELLS
    cells = set()
    for path in paths:
        obs = load_observations(path)
        for u, v in obs.image_xy[np.all(np.isfinite(obs.image_xy), axis=1)]:
            if 0 <= u < 320 and 0 <= v < 240:
                cells.add((int(u * nx / 320), int(v * ny / 240)))
    return len(cells) / (nx * ny)


def test_the_job_draws_a_report_of_every_camera_and_the_extrinsics(board_report) -> None:
    c, resource, _, files = board_report
    cal_id = resource.rsplit("/", 1)[1]
    svc = c.app.state.services
    assert (svc.store.dir_for(cal_id) / "report" / "report.html").is_file()  # before a request
    r = c.get(f"{resource}/report.html")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    page = r.text
    assert "<meta name='phasecal-report' content='phasecal.rig-report/1'>" in page
    cams = table_rows(page, "cameras")
    assert [row[0] for row in cams] == ["A", "B"]
    for row in cams:
        assert row[1] == "opencv5" and row[2] == "320 x 240" and float(row[3]) > 0
        assert float(row[7]) == VIEWS - 1  # training views of the joint fit
        # coverage counted from the training shots' detected points, not the held-out one
        training = [p for shot, p in files[row[0]].items() if shot != HELD]
        assert row[-1] == f"{_covered_fraction(training):.0%}"
    ext = c.get(f"{resource}/rig").json()["cameras"]["B"]["extrinsics"]
    check_extrinsics_row(page, "B", ext)
    assert re.search(r'id="verdict" data-status="(pass|warn|fail)"', page)
    assert "B: baseline 1-sigma" in page and "A: coverage of its sensor" in page
    held = re.search(r"<h2>Held-out views</h2>(.*?)<h2>", page, re.S).group(1)
    assert f"<td>{HELD}</td>" in held and "<td>B</td>" in held
    links = [h.replace("&amp;", "&")
             for h in re.findall(r'class="download" href="([^"]+)"', page)]
    assert f"{resource}/rig" in links
    assert all(h.startswith(f"{resource}/rig") for h in links)
    for href in [f"{resource}/rig", *[h for h in links if "format=opencv-stereo" in h
                                      or "format=ros-transforms" in h
                                      or ("camera=B" in h and "format=opencv-yaml" in h)]]:
        assert c.get(href).status_code == 200, href
    pngs = re.findall(r'src="(report/coverage_\d\d\.png)"', page)
    assert len(pngs) == 2
    for png in pngs:
        img = c.get(f"{resource}/{png}")
        assert img.status_code == 200 and img.headers["content-type"] == "image/png"
        assert img.content[:4] == b"\x89PNG"


def test_the_report_downloads_whole_and_is_drawn_again_when_missing(board_report) -> None:
    c, resource, _, _ = board_report
    cal_id = resource.rsplit("/", 1)[1]
    saved = c.get(f"{resource}/report.html", params={"download": 1})
    assert saved.status_code == 200
    assert f'filename="{cal_id}-report.html"' in saved.headers["content-disposition"]
    assert 'src="data:image/png;base64,' in saved.text and 'src="report/' not in saved.text
    shutil.rmtree(c.app.state.services.store.dir_for(cal_id) / "report")
    assert c.get(f"{resource}/report/coverage_01.png").status_code == 200
    assert c.get(f"{resource}/report/coverage_07.png").status_code == 404
    assert c.get(f"{resource}/report/rig.json").status_code == 404


def test_no_report_for_a_calibration_running_failed_or_unknown(board_report) -> None:
    c, _, cameras, _ = board_report
    svc = c.app.state.services
    cal_id = "cal_00000000000000bb"
    with svc.db.session() as s:
        s.add(TargetRigCalibrationRecord(
            id=cal_id, cameras=cameras, reference="A", status="running",
            camera_models={"A": "opencv5", "B": "opencv5"}, job_id="job_running"))
    page = c.get(f"/target-rig-calibrations/{cal_id}/report.html")
    assert page.status_code == 202 and "id='drawing'" in page.text
    png = c.get(f"/target-rig-calibrations/{cal_id}/report/coverage_00.png")
    assert png.status_code == 409 and png.json()["title"]
    with svc.db.session() as s:
        s.get(TargetRigCalibrationRecord, cal_id).status = "failed"
    r = c.get(f"/target-rig-calibrations/{cal_id}/report.html")
    assert r.status_code == 409 and "failed" in r.json()["detail"]
    assert c.delete(f"/target-rig-calibrations/{cal_id}").status_code == 204
    assert c.get(f"/target-rig-calibrations/{cal_id}/report.html").status_code == 404


def test_coverage_comes_from_maps_or_observations_not_both() -> None:
    with pytest.raises(ValueError, match="not both"):
        RigReportInputs("rig.json", "result.json", {"A": ["a.npz"]}, ReportHeader("t"),
                        observations={"A": ["o.npz"]})
