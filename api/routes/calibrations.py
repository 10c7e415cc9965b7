"""Calibrations: start a fit job, read statistics, model, exports, plot; project/unproject."""

from __future__ import annotations

import time
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Query
from fastapi.responses import JSONResponse, Response
from sqlalchemy import select

from api.db import CalibrationRecord, PoseRecord
from api.jobs.calibrations import CalibrateJob
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, accepted, get_session
from api.routes.points import json_rows, point_rows
from api.schemas import (
    MAX_OFFSET,
    Calibration,
    CalibrationCreate,
    ProjectRequest,
    ProjectResponse,
    UnprojectRequest,
    UnprojectResponse,
)
from api.services import Services, get_services
from api.store import check_id, new_id
from calibration import CameraModel, load_model, model_spec

router = APIRouter(tags=["calibrations"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]

MIN_POINT_NORM_MM = 1e-6  # closer to the camera centre than this: no direction, a NaN row
EXPORTS = {
    "model.json": "application/json",
    "result.json": "application/json",
    "opencv.yaml": "application/x-yaml",
    "camera_info.yaml": "application/x-yaml",
    "residuals.png": "image/png",
}


def _cal_dict(c: CalibrationRecord) -> dict[str, Any]:
    return {"id": c.id, "session_id": c.session_id, "model": c.model, "pose_ids": c.pose_ids,
            "heldout_pose_ids": c.heldout_pose_ids, "status": c.status, "job_id": c.job_id,
            "stats": c.stats, "exports": c.exports, "error": c.error, "created_at": c.created_at}


def _get_cal(s: Any, cal_id: str) -> CalibrationRecord:
    check_id(cal_id, "cal", "calibration")
    rec = s.get(CalibrationRecord, cal_id)
    if rec is None:
        raise Problem(404, "not-found", f"calibration {cal_id!r} does not exist")
    return rec


def _check_poses(s: Any, session_id: str, ids: list[str], field: str,
                 sizes: dict[tuple[int | None, int | None], str]) -> None:
    """Every id is a decoded pose of the session; all poses share one image size.

    Poses flagged by the capture integrity check are accepted only when named explicitly.
    """
    for pid in ids:
        check_id(pid, "pose", "pose")
        p = s.get(PoseRecord, pid)
        if p is None or p.session_id != session_id:
            raise Problem(422, "validation-error",
                          f"{field}: pose {pid!r} is not a pose of session {session_id}")
        if p.status not in ("ready", "flagged"):
            raise Problem(409, "not-ready", f"{field}: pose {pid} is {p.status}, not ready")
        sizes.setdefault((p.width, p.height), pid)
        if len(sizes) > 1:
            (w0, h0), first = next(iter(sizes.items()))
            raise Problem(422, "validation-error",
                          f"{field}: pose {pid} is {p.width}x{p.height} px but pose {first} is "
                          f"{w0}x{h0} px; one calibration needs one camera resolution")


@router.post("/sessions/{session_id}/calibrations", status_code=202, response_model=None,
             responses={202: {"description": "calibration job accepted; Location: /jobs/<id>"}})
def create_calibration(session_id: str, request: CalibrationCreate, svc: Svc) -> JSONResponse:
    """Calibrate chosen poses (default: every ready pose not held out) with one model (a job)."""
    body = request.root
    options = body.options.model_dump(mode="json", exclude_unset=True)
    cid = new_id("cal")
    with svc.db.claim_session() as s:
        get_session(s, session_id)
        if body.pose_ids is None:
            pose_ids = list(s.scalars(
                select(PoseRecord.id).where(PoseRecord.session_id == session_id,
                                            PoseRecord.status == "ready")
                .order_by(PoseRecord.index)))
            pose_ids = [p for p in pose_ids if p not in body.heldout_pose_ids]
        else:
            pose_ids = list(dict.fromkeys(body.pose_ids))
        if not pose_ids:
            raise Problem(409, "no-poses", f"session {session_id} has no ready poses to calibrate")
        sizes: dict[tuple[int | None, int | None], str] = {}
        _check_poses(s, session_id, pose_ids, "pose_ids", sizes)
        _check_poses(s, session_id, body.heldout_pose_ids, "heldout_pose_ids", sizes)
        need = model_spec(body.model).min_poses
        if len(pose_ids) < need:
            raise Problem(422, "validation-error",
                          f"pose_ids: {body.model} needs >= {need} training poses, got "
                          f"{len(pose_ids)}")
        overlap = set(pose_ids) & set(body.heldout_pose_ids)
        if overlap:
            raise Problem(422, "validation-error",
                          f"heldout_pose_ids: {sorted(overlap)[0]} is also in pose_ids")
        job = CalibrateJob(svc=svc, session_id=session_id, cal_id=cid, model=body.model,
                           pose_ids=pose_ids, heldout_pose_ids=list(body.heldout_pose_ids),
                           options=options)
        state = svc.jobs.create(s, job)
        s.add(CalibrationRecord(id=cid, session_id=session_id, model=body.model,
                                pose_ids=pose_ids, heldout_pose_ids=body.heldout_pose_ids,
                                options=options, status="queued", job_id=state.id,
                                exports=[], created_at=time.time()))
    return accepted(svc.jobs.start(state.id, job))


@router.get("/calibrations", response_model=list[Calibration])
def list_calibrations(svc: Svc, session_id: str | None = None,
                      limit: Annotated[int, Query(ge=1, le=500)] = 100,
                      offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
                      ) -> list[dict[str, Any]]:
    """Calibrations, newest first, optionally of one session."""
    with svc.db.session() as s:
        q = select(CalibrationRecord)
        if session_id is not None:
            q = q.where(CalibrationRecord.session_id == session_id)
        recs = s.scalars(q.order_by(CalibrationRecord.created_at.desc()).limit(limit)
                         .offset(offset)).all()
        return [_cal_dict(c) for c in recs]


@router.get("/calibrations/{cal_id}", response_model=Calibration)
def read_calibration(cal_id: str, svc: Svc) -> dict[str, Any]:
    """One calibration with its statistics once it succeeded."""
    with svc.db.session() as s:
        return _cal_dict(_get_cal(s, cal_id))


def _succeeded(svc: Services, cal_id: str) -> CalibrationRecord:
    with svc.db.session() as s:
        c = _get_cal(s, cal_id)
    if c.status != "succeeded":
        raise Problem(409, "not-ready", f"calibration {cal_id} is {c.status}; outputs exist "
                      "once it succeeded")
    return c


@router.get("/calibrations/{cal_id}/files/{name}", response_class=Response,
            responses={200: {"content": {"application/json": {}, "application/x-yaml": {},
                                         "image/png": {}}}})
def download(cal_id: str, name: str, svc: Svc) -> Response:
    """model.json, result.json, opencv.yaml, camera_info.yaml or residuals.png."""
    if name not in EXPORTS:
        raise Problem(404, "not-found", f"file {name!r}: expected one of {sorted(EXPORTS)}")
    c = _succeeded(svc, cal_id)
    if name not in c.exports:
        raise Problem(404, "not-found", f"calibration {cal_id} ({c.model}) has no {name}; "
                      f"available: {c.exports}")
    path = svc.store.file(cal_id, name)
    return Response(path.read_bytes(), media_type=EXPORTS[name])


def fitted_model(svc: Services, cal_id: str) -> CameraModel:
    """The model of a succeeded calibration (404 unknown id, 409 not succeeded yet): what
    every route that applies a calibration to points or exports it starts from."""
    _succeeded(svc, cal_id)
    return load_model(svc.store.file(cal_id, "model.json"))


@router.post("/calibrations/{cal_id}/project", response_model=ProjectResponse)
def project(cal_id: str, body: ProjectRequest, svc: Svc) -> dict[str, Any]:
    """Camera-frame points (mm) -> pixels with the fitted model."""
    pts = point_rows(body.points, 3)
    model = fitted_model(svc, cal_id)
    # the camera centre (0,0,0) has no direction: a NaN row (docs/formats.md), not a failed fit
    seen = np.linalg.norm(pts, axis=1) > MIN_POINT_NORM_MM
    pixels = np.full((len(pts), 2), np.nan)
    if seen.any():
        pixels[seen] = model.project(pts[seen])
    return {"pixels": json_rows(pixels)}


@router.post("/calibrations/{cal_id}/unproject", response_model=UnprojectResponse)
def unproject(cal_id: str, body: UnprojectRequest, svc: Svc) -> dict[str, Any]:
    """Pixels -> rays (origins mm, unit directions) with the fitted model."""
    px = point_rows(body.pixels, 2)
    origins, dirs = fitted_model(svc, cal_id).unproject(px)
    return {"origins": json_rows(origins), "directions": json_rows(dirs)}
