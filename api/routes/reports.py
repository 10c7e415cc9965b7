"""Calibration report pages, their images, and model-versus-model differences."""

from __future__ import annotations

import json
import re
from typing import Annotated, Any

from fastapi import APIRouter, Depends
from fastapi.responses import HTMLResponse, Response

from api.problems import Problem
from api.reports import diff_dir, report_dir
from api.routes.common import PROBLEM_RESPONSES
from api.services import Services, get_services

router = APIRouter(tags=["reports"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
_PNG = re.compile(r"[a-z]+(_[0-9]{2})?\.png")


@router.get("/calibrations/{cal_id}/report.html", response_class=HTMLResponse)
def report_page(cal_id: str, svc: Svc) -> HTMLResponse:
    """The calibration report: numbers, residual fields per pose, histogram, radial profile,
    ray-uncertainty map, coverage, held-out poses (drawn from stored data on first request)."""
    page = (report_dir(svc, cal_id) / "report.html").read_text(encoding="utf-8")
    # Images are linked by file name; this page lives one level above them.
    page = re.sub(r'src="([a-z_0-9]+\.png)"', r'src="report/\1"', page)
    return HTMLResponse(page)


@router.get("/calibrations/{cal_id}/report/{name}", response_class=Response,
            responses={200: {"content": {"image/png": {}, "text/html": {}}}})
def report_file(cal_id: str, name: str, svc: Svc) -> Response:
    """One PNG of the report (names as linked from report.html), or report.html itself."""
    if name != "report.html" and not _PNG.fullmatch(name):
        raise Problem(404, "not-found", f"report file {name!r}: expected report.html or a "
                      "PNG named in it")
    path = report_dir(svc, cal_id) / name
    if not path.is_file():
        raise Problem(404, "not-found", f"calibration {cal_id}'s report has no {name}")
    media = "text/html" if name.endswith(".html") else "image/png"
    return Response(path.read_bytes(), media_type=media)


@router.get("/calibrations/{cal_a}/diff/{cal_b}")
def diff(cal_a: str, cal_b: str, svc: Svc) -> dict[str, Any]:
    """Ray-angle difference of two calibrations after the best aligning rotation, on the pixels
    their poses saw: RMS, 95th percentile and max (urad), the rotation, and the map's URL."""
    out = json.loads((diff_dir(svc, cal_a, cal_b) / "diff.json").read_text())
    out["image"] = f"/calibrations/{cal_a}/diff/{cal_b}/diff.png"
    return out


@router.get("/calibrations/{cal_a}/diff/{cal_b}/diff.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}})
def diff_image(cal_a: str, cal_b: str, svc: Svc) -> Response:
    """The difference map (urad, log colour scale)."""
    return Response((diff_dir(svc, cal_a, cal_b) / "diff.png").read_bytes(),
                    media_type="image/png")
