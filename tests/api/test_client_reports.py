"""The clients' `download_report`: the route picked from what names the calibration (an id or
a calibration record: /calibrations; a target rig's record or job: /target-rig-calibrations),
a report not drawn yet refused without touching the file, and end to end against a real
`phasecal serve`: a rig calibrated from target sessions, its report saved whole by the sync
and the async client, with the numbers `phasecal report` draws from the served rig model
and the same observation files."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from api.cli import main
from api.client import AsyncPhasecalClient, PhasecalClient, ServiceError
from tests.api.rig_report_checks import table_rows
from tests.api.test_client_core import Face
from tests.api_server import ServerProcess
from tests.calibration.rig.conftest import SCREEN, board_view_files, two_pinholes

PAGE = b"<!doctype html><title>report</title><img src=\"data:image/png;base64,AAAA\">"
NAMED = [  # what names the calibration -> the route it is asked at
    ("cal_1", "/calibrations/cal_1/report.html"),
    ({"id": "cal_2", "session_id": "ses_1", "model": "opencv5"},
     "/calibrations/cal_2/report.html"),
    ({"id": "job_1", "session_id": "ses_1", "resource": "/calibrations/cal_3"},
     "/calibrations/cal_3/report.html"),
    ({"id": "cal_4", "cameras": {"A": {}}, "reference": "A"},
     "/target-rig-calibrations/cal_4/report.html"),
    ({"id": "job_2", "session_id": None, "resource": "/target-rig-calibrations/cal_5"},
     "/target-rig-calibrations/cal_5/report.html"),
]


@pytest.mark.parametrize("kind", ["sync", "async"])
def test_the_route_follows_the_record_and_a_report_not_drawn_is_refused(kind: str,
                                                                        tmp_path: Path) -> None:
    asked: list[httpx.Request] = []
    drawing = {"cal_1"}

    def handler(request: httpx.Request) -> httpx.Response:
        asked.append(request)
        if request.url.path.split("/")[2] in drawing:
            return httpx.Response(202, headers={"Retry-After": "2"}, text="being drawn")
        return httpx.Response(200, content=PAGE, headers={"content-type": "text/html"})

    face = Face(kind, handler)
    dest = tmp_path / "report.html"
    for named, path in NAMED[1:]:
        assert face.call("download_report", named, dest) == dest
        assert asked[-1].url.path == path and asked[-1].url.params["download"] == "1"
        assert dest.read_bytes() == PAGE
    dest.write_text("the report saved before")
    with pytest.raises(ServiceError) as err:
        face.call("download_report", NAMED[0][0], dest)
    assert err.value.status == 202 and err.value.type.endswith("/not-ready")
    assert asked[-1].url.path == NAMED[0][1] and "ask again in 2 s" in err.value.detail
    assert dest.read_text() == "the report saved before"
    assert [p.name for p in tmp_path.iterdir()] == ["report.html"]  # no partial file left
    with pytest.raises(ValueError, match="not one calibration"):
        face.call("download_report", {"id": "job_3", "resource": "/calibrations"}, dest)


def _upload_views(client: PhasecalClient, inputs: list[str]) -> dict[str, dict[str, Any]]:
    """One target session per camera holding its CAMERA/SHOT=PATH observation files."""
    cameras: dict[str, dict[str, Any]] = {}
    for arg in inputs:
        name, path = arg.split("=", 1)
        cam, shot = name.split("/")
        if cam not in cameras:
            ses = client.post("/target-sessions", {"name": cam, "target": "points"})
            cameras[cam] = {"session_id": ses["id"], "views": {}}
        r = client.request("POST", f"/target-sessions/{cameras[cam]['session_id']}/views",
                           files={"file": (Path(path).name, Path(path).read_bytes())})
        cameras[cam]["views"][shot] = r.json()["id"]
    return cameras


def test_a_target_rig_report_saved_by_both_clients(tmp_path: Path) -> None:
    inputs = board_view_files(tmp_path, two_pinholes(), SCREEN, 4, np.random.default_rng(5))
    srv = ServerProcess(tmp_path / "data")
    srv.start()
    try:
        with PhasecalClient(srv.url) as client:
            job = client.wait(client.calibrate_target_rig(_upload_views(client, inputs),
                                                          "opencv5"), timeout_s=300)
            saved = client.download_report(job, tmp_path / "sync.html")
            record = client.get_target_rig_calibration(job["resource"].rsplit("/", 1)[1])
            rig = client.get(f"{job['resource']}/rig")

        async def save_async() -> Path:
            async with AsyncPhasecalClient(srv.url) as aio:
                return await aio.download_report(record, tmp_path / "async.html")

        saved_async = asyncio.run(save_async())
    finally:
        srv.stop()
    page = saved.read_text()
    assert "<meta name='phasecal-report' content='phasecal.rig-report/1'>" in page
    assert "<table id='cameras'" in page and "<td>A</td>" in page and "<td>B</td>" in page
    assert "<table id='extrinsics'" in page
    assert page.count('src="data:image/png;base64,') == 2 and 'src="report/' not in page
    assert saved_async.read_text() == page
    # the command line draws the same numbers from the served rig model and the same files
    (tmp_path / "rig.json").write_text(json.dumps(rig))
    assert main(["report", "--model", str(tmp_path / "rig.json"), "--observations", *inputs,
                 "-o", str(tmp_path / "cli")]) == 0
    cli = (tmp_path / "cli" / "report.html").read_text()
    for table in ("cameras", "extrinsics"):
        assert table_rows(cli, table) == table_rows(page, table)
