"""Calibration report pages, their images and downloads, and model-versus-model differences."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query
from fastapi.responses import HTMLResponse, Response

from api.jobs.rig_calibrations import is_rig_calibration, rig_report_folder
from api.problems import Problem
from api.reports import (
    calibration,
    compare_links,
    diff_dir,
    diff_summary,
    drawing_page,
    ready_report,
)
from api.routes.common import (
    PROBLEM_RESPONSES,
    check_report_file,
    report_file_response,
    report_page_response,
)
from api.services import Services, get_services
from calibration import with_links

router = APIRouter(tags=["reports"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
_DIFF_FILES = {"diff.html": "text/html", "diff.png": "image/png", "diff_sigma.png": "image/png"}


@router.get("/calibrations/{cal_id}/report.html", response_class=HTMLResponse,
            responses={202: {"content": {"text/html": {}},
                             "description": "the report is being drawn: a page that says so "
                                            "and reloads itself"}})
def report_page(cal_id: str, svc: Svc, download: Annotated[bool, Query(
        description="the report as one self-contained file (images inlined) to save")] = False,
                ) -> HTMLResponse:
    """The calibration report: verdict against stated thresholds, downloads of the model and
    its exports, numbers, residual fields per pose, histogram, radial profile, ray-uncertainty
    map, coverage, held-out poses (a rig's: every camera and the extrinsics with their
    sigma). Drawn by the calibration job; until it is in place (202) a page that says so and
    reloads itself."""
    rec = calibration(svc, cal_id)
    rig = is_rig_calibration(rec)
    folder = rig_report_folder(svc, rec) if rig else ready_report(svc, cal_id)
    if folder is None:
        return HTMLResponse(drawing_page(cal_id, rec.status),
                            status_code=202, headers={"Retry-After": "2"})
    page = (folder / "report.html").read_text(encoding="utf-8")
    if not rig:  # a rig has no single-camera model to compare with
        page = with_links(page, compare_links(svc, cal_id))
    return report_page_response(cal_id, folder, page, download)


@router.get("/calibrations/{cal_id}/report/{name}", response_class=Response,
            responses={200: {"content": {"image/png": {}, "text/html": {}}}})
def report_file(cal_id: str, name: str, svc: Svc) -> Response:
    """One PNG of the report (names as linked from report.html), or report.html itself."""
    check_report_file(name)
    rec = calibration(svc, cal_id)
    folder = rig_report_folder(svc, rec) if is_rig_calibration(rec) else ready_report(svc, cal_id)
    if folder is None:
        raise Problem(409, "not-ready", f"calibration {cal_id}'s report is being drawn; "
                      "ask again in a few seconds")
    return report_file_response(cal_id, name, folder)


@router.get("/calibrations/{cal_a}/diff/{cal_b}")
def diff(cal_a: str, cal_b: str, svc: Svc) -> dict[str, Any]:
    """Ray-angle difference of two calibrations after the best aligning rotation, on the pixels
    their poses saw, against the two fits' combined ray uncertainty: median, 95th percentile,
    max and RMS (urad), the fraction beyond 2 combined sigma, whether the models agree, the
    rotation, and the URLs of the page and its maps."""
    out = diff_summary(diff_dir(svc, cal_a, cal_b))
    base = f"/calibrations/{cal_a}/diff/{cal_b}"
    out["image"] = f"{base}/diff.png"
    out["page"] = f"{base}/diff.html"
    if "sigma_image" in out:
        out["sigma_image"] = f"{base}/diff_sigma.png"
    return out


@router.get("/calibrations/{cal_a}/diff/{cal_b}/{name}", response_class=Response,
            responses={200: {"content": {"text/html": {}, "image/png": {}}}})
def diff_file(cal_a: str, cal_b: str, name: str, svc: Svc) -> Response:
    """The difference as a page (diff.html) and its maps: diff.png (urad, log colour scale),
    diff_sigma.png (difference over the combined 1-sigma)."""
    if name not in _DIFF_FILES:
        raise Problem(404, "not-found", f"diff file {name!r}: expected one of "
                      f"{sorted(_DIFF_FILES)}")
    path = diff_dir(svc, cal_a, cal_b) / name
    if not path.is_file():
        raise Problem(404, "not-found", f"the difference of {cal_a} and {cal_b} has no {name} "
                      "(the uncertainty of a model is not available)")
    return Response(path.read_bytes(), media_type=_DIFF_FILES[name])
