"""Helpers shared by the route modules: record lookups, 202 answers, error responses."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any

from fastapi import Query
from fastapi.responses import HTMLResponse, JSONResponse, Response

from api.db import PoseRecord, SessionRecord
from api.pose_path import pose_cameras
from api.problems import Problem
from api.schemas import ProblemDetail
from api.store import check_id
from calibration import self_contained

REPORT_PNG = re.compile(r"[a-z]+(_[0-9]{2})?\.png")  # the PNGs a report page links


def _problem(description: str) -> dict[str, Any]:
    return {"description": description, "model": ProblemDetail,
            "content": {"application/problem+json": {}}}


PROBLEM_RESPONSES: dict[int | str, dict[str, Any]] = {
    400: _problem("Malformed request body"),
    404: _problem("Unknown id"),
    409: _problem("Conflict with the resource's state"),
    413: _problem("Request body too large"),
    422: _problem("Invalid input"),
}

#: The answer of a stream route beyond its caps (`api.stream_limits`).
TOO_MANY_STREAMS: dict[int | str, dict[str, Any]] = {
    429: {**_problem("Too many open streams from this client or in all; see Retry-After"),
          "headers": {"Retry-After": {"description": "seconds to wait before retrying",
                                      "schema": {"type": "integer"}}}},
}


#: `?camera=NAME`: one camera of a pose captured on several cameras (the pose's `cameras`).
CameraQuery = Annotated[str | None, Query(
    pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$",
    description="the camera of a pose captured on several cameras (see the pose's cameras)")]


def accepted(job: dict[str, Any]) -> JSONResponse:
    """202 Accepted with the job body and `Location: /jobs/<id>`."""
    return JSONResponse(job, status_code=202, headers={"Location": f"/jobs/{job['id']}"})


def get_session(s: Any, session_id: str) -> SessionRecord:
    """The session record or a 404 problem."""
    check_id(session_id, "ses", "session")
    rec = s.get(SessionRecord, session_id)
    if rec is None:
        raise Problem(404, "not-found", f"session {session_id!r} does not exist")
    return rec


def get_pose(s: Any, session_id: str, pose_id: str) -> PoseRecord:
    """The pose record of that session or a 404 problem."""
    get_session(s, session_id)
    check_id(pose_id, "pose", "pose")
    rec = s.get(PoseRecord, pose_id)
    if rec is None or rec.session_id != session_id:
        raise Problem(404, "not-found",
                      f"pose {pose_id!r} does not exist in session {session_id!r}")
    return rec


def pose_to_dict(p: PoseRecord, pose_dir: Path | None = None) -> dict[str, Any]:
    """A pose record as API data; `cameras` lists each camera of a several-camera pose
    (found in its folder `pose_dir`) with its status, None for one camera."""
    return {
        "id": p.id, "session_id": p.session_id, "index": p.index, "source": p.source,
        "status": p.status, "job_id": p.job_id, "valid_pixels": p.valid_pixels,
        "width": p.width, "height": p.height, "frames_done": p.frames_done,
        "screen_pose": p.screen_pose, "error": p.error, "created_at": p.created_at,
        "cameras": None if pose_dir is None else pose_cameras(pose_dir, p.status, p.error),
    }


def report_page_response(cal_id: str, folder: Path, page: str, download: bool) -> HTMLResponse:
    """A drawn report page (`page`, from `folder`): one self-contained file to save with
    `download`, else served with its images linked under `report/` (this page lives one
    level above them)."""
    if download:
        return HTMLResponse(self_contained(page, folder), headers={
            "Content-Disposition": f'attachment; filename="{cal_id}-report.html"'})
    return HTMLResponse(re.sub(r'src="([a-z_0-9]+\.png)"', r'src="report/\1"', page))


def check_report_file(name: str) -> None:
    """A 404 unless `name` is report.html or a PNG name a report links."""
    if name != "report.html" and not REPORT_PNG.fullmatch(name):
        raise Problem(404, "not-found", f"report file {name!r}: expected report.html or a "
                      "PNG named in it")


def report_file_response(cal_id: str, name: str, folder: Path) -> Response:
    """File `name` (checked by `check_report_file`) of a drawn report in `folder`."""
    path = folder / name
    if not path.is_file():
        raise Problem(404, "not-found", f"calibration {cal_id}'s report has no {name}")
    media = "text/html" if name.endswith(".html") else "image/png"
    return Response(path.read_bytes(), media_type=media)
