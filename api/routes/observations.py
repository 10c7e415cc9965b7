"""Target sessions: a passive target (a board, or surveyed points) instead of a plan; views
uploaded as observation files or as images the board is detected in (server-side), and
calibrations of chosen views in pixel space (every parametric model).

A fit of a few dozen views takes well under a second, so a calibration is answered in its
request (201 with its statistics) rather than as a job.
"""

from __future__ import annotations

import shutil
import time
from typing import Annotated, Any

from fastapi import APIRouter, Depends, File, UploadFile
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import BaseModel, Field
from sqlalchemy import func, select

from api.db import TargetCalibrationRecord, TargetSessionRecord, TargetViewRecord
from api.observations_upload import POINTS_TARGET, observations_from_upload
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES
from api.schemas import IdStr, strict_config
from api.services import Services, get_services
from api.store import check_id, new_id
from calibration import (
    PARAMETRIC,
    TargetSpec,
    TargetSpecError,
    calibrate_observations,
    write_model_folder,
    write_uncertainty_png,
)
from calibration.shared.atomic import atomic_path
from calibration.shared.observations import load_observations, save_observations

router = APIRouter(tags=["target sessions"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
MAX_VIEWS = 2000


class TargetSessionCreate(BaseModel):
    """A session of a passive target."""

    model_config = strict_config({"name": "bench-board", "target": "chessboard:9x6:25"})
    name: str = Field(default="", max_length=200)
    target: str = Field(max_length=200, description=(
        'chessboard:COLSxROWS:SQUARE_MM (inner corners), charuco:COLSxROWS:SQUARE_MM:'
        'MARKER_MM:DICT (squares), or "points" (surveyed points: observation files only)'))


class TargetSession(BaseModel):
    """A target session and how many views it holds."""

    id: str
    name: str
    target: str
    views: int
    created_at: float


class TargetView(BaseModel):
    """One view: where it came from and how many target points it has."""

    id: str
    index: int
    name: str
    source: str
    points: int
    width: int
    height: int
    created_at: float


class TargetCalibrationCreate(BaseModel):
    """A pixel-space calibration of chosen views (default: all)."""

    model_config = strict_config({"model": "opencv5", "options": {"target": "fit"},
                                  "cross_validate": 2})
    model: str = Field(description=f"one of {list(PARAMETRIC)}")
    options: dict[str, Any] = Field(default_factory=dict, description=(
        "target (flat|fit), weights (observed|equal), outlier_sigma, outlier_rounds, "
        "thin_prism, max_iterations (docs/targets.md)"))
    view_ids: list[IdStr] | None = Field(default=None, max_length=MAX_VIEWS)
    cross_validate: int = Field(default=0, ge=0, le=10,
                                description="fit this many disjoint view sets and compare")


class TargetCalibration(BaseModel):
    """A calibration of a target session: model, views and statistics."""

    id: str
    session_id: str
    model: str
    view_ids: list[str]
    options: dict[str, Any]
    cross_validate: int
    stats: dict[str, Any]
    created_at: float


def _session(s: Any, session_id: str) -> TargetSessionRecord:
    check_id(session_id, "ses", "target session")
    rec = s.get(TargetSessionRecord, session_id)
    if rec is None:
        raise Problem(404, "not-found", f"target session {session_id!r} does not exist")
    return rec


def _session_dict(s: Any, rec: TargetSessionRecord) -> dict[str, Any]:
    count = s.scalar(select(func.count()).where(TargetViewRecord.session_id == rec.id))
    return {"id": rec.id, "name": rec.name, "target": rec.target, "views": int(count or 0),
            "created_at": rec.created_at}


def _view_dict(rec: TargetViewRecord) -> dict[str, Any]:
    return {k: getattr(rec, k) for k in TargetView.model_fields}


def _cal_dict(rec: TargetCalibrationRecord) -> dict[str, Any]:
    return {k: getattr(rec, k) for k in TargetCalibration.model_fields}


@router.post("/target-sessions", status_code=201, response_model=TargetSession)
def create_target_session(body: TargetSessionCreate, svc: Svc) -> JSONResponse:
    """Create a session of a board (chessboard, ChArUco) or of surveyed points."""
    target = body.target.strip()
    if target != POINTS_TARGET:
        try:
            target = TargetSpec.parse(target).describe()
        except TargetSpecError as exc:
            raise Problem(422, "validation-error", f"target: {exc}") from None
    sid = new_id("ses")
    with svc.db.session() as s:
        rec = TargetSessionRecord(id=sid, name=body.name, target=target, created_at=time.time())
        s.add(rec)
        s.flush()
        out = _session_dict(s, rec)
    return JSONResponse(out, status_code=201, headers={"Location": f"/target-sessions/{sid}"})


@router.get("/target-sessions/{session_id}", response_model=TargetSession)
def read_target_session(session_id: str, svc: Svc) -> dict[str, Any]:
    """One target session."""
    with svc.db.session() as s:
        return _session_dict(s, _session(s, session_id))


@router.post("/target-sessions/{session_id}/views", status_code=201, response_model=TargetView)
def upload_view(session_id: str, svc: Svc, file: Annotated[UploadFile, File()]) -> JSONResponse:
    """Add a view: an observations NPZ, or an image the session's board is detected in."""
    name = file.filename or "view"
    with svc.db.session() as s:
        target = _session(s, session_id).target
        first = s.execute(select(TargetViewRecord.width, TargetViewRecord.height).where(
            TargetViewRecord.session_id == session_id).limit(1)).first()
    obs, source = observations_from_upload(file.file.read(), name, target,
                                           svc.config.max_upload_bytes)
    if first is not None and tuple(first) != tuple(obs.image_size):
        raise Problem(422, "invalid-observations",
                      f"{name}: image_size: {obs.image_size[0]}x{obs.image_size[1]}, the "
                      f"session's views are {first[0]}x{first[1]}")
    vid = new_id("pose")
    path = svc.store.file(session_id, f"{vid}.npz")
    save_observations(obs, path)
    try:
        with svc.db.session() as s:
            _session(s, session_id)
            index = s.scalar(select(func.count()).where(
                TargetViewRecord.session_id == session_id)) or 0
            if index >= MAX_VIEWS:
                raise Problem(409, "too-many-views", f"target session {session_id} holds "
                              f"{MAX_VIEWS} views, the most one session may")
            rec = TargetViewRecord(id=vid, session_id=session_id, index=int(index),
                                   name=name[:200], source=source, points=obs.used_count(),
                                   width=obs.image_size[0], height=obs.image_size[1],
                                   created_at=time.time())
            s.add(rec)
    except BaseException:  # no file is left without its record
        path.unlink(missing_ok=True)
        raise
    return JSONResponse(_view_dict(rec), status_code=201,
                        headers={"Location": f"/target-sessions/{session_id}/views/{vid}"})


@router.get("/target-sessions/{session_id}/views", response_model=list[TargetView])
def list_views(session_id: str, svc: Svc) -> list[dict[str, Any]]:
    """The session's views in upload order."""
    with svc.db.session() as s:
        _session(s, session_id)
        rows = s.scalars(select(TargetViewRecord).where(
            TargetViewRecord.session_id == session_id).order_by(TargetViewRecord.index)).all()
        return [_view_dict(r) for r in rows]


@router.get("/target-sessions/{session_id}/views/{view_id}/observations.npz",
            response_class=Response, responses={200: {"content": {"application/zip": {}}}})
def download_view(session_id: str, view_id: str, svc: Svc) -> FileResponse:
    """The view as a `phasecal.observations/1` NPZ (detected corners, for an image)."""
    check_id(view_id, "pose", "view")
    with svc.db.session() as s:
        _session(s, session_id)
        rec = s.get(TargetViewRecord, view_id)
        if rec is None or rec.session_id != session_id:
            raise Problem(404, "not-found", f"view {view_id!r} is not in {session_id}")
    return FileResponse(svc.store.file(session_id, f"{view_id}.npz"),
                        media_type="application/zip", filename=f"{rec.name}.npz")


@router.post("/target-sessions/{session_id}/calibrations", status_code=201,
             response_model=TargetCalibration)
def create_calibration(session_id: str, body: TargetCalibrationCreate, svc: Svc
                       ) -> JSONResponse:
    """Fit a parametric or sGCC model to the chosen views in pixel space; 422 naming the
    field for a model or options the fit refuses."""
    with svc.db.session() as s:
        _session(s, session_id)
        rows = s.scalars(select(TargetViewRecord).where(
            TargetViewRecord.session_id == session_id).order_by(TargetViewRecord.index)).all()
    by_id = {r.id: r for r in rows}
    ids = body.view_ids if body.view_ids is not None else [r.id for r in rows]
    unknown = [v for v in ids if v not in by_id]
    if unknown:
        raise Problem(422, "validation-error", f"view_ids: not views of {session_id}: "
                      f"{unknown[:5]}")
    if len(set(ids)) != len(ids):
        raise Problem(422, "validation-error", "view_ids: a view is listed twice")
    views = [load_observations(svc.store.file(session_id, f"{v}.npz")) for v in ids]
    try:
        result = calibrate_observations(views, body.model, options=body.options,
                                        cross_validate_folds=body.cross_validate)
    except ValueError as exc:  # model, options.<field>, observations: ... or cross-validate
        raise Problem(422, "validation-error", str(exc)) from None
    cid = new_id("cal")
    folder = svc.store.dir_for(cid)
    try:
        written = write_model_folder(result, body.model, folder)
        with atomic_path(folder / "uncertainty.png") as tmp:
            write_uncertainty_png(result, tmp)
        with svc.db.session() as s:
            _session(s, session_id)
            rec = TargetCalibrationRecord(
                id=cid, session_id=session_id, model=body.model, view_ids=list(ids),
                options=body.options, cross_validate=body.cross_validate,
                stats=written["stats"], created_at=time.time())
            s.add(rec)
    except BaseException:  # no folder is left without its record
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return JSONResponse(_cal_dict(rec), status_code=201, headers={
        "Location": f"/target-sessions/{session_id}/calibrations/{cid}"})


def _calibration(svc: Services, session_id: str, cal_id: str) -> TargetCalibrationRecord:
    check_id(cal_id, "cal", "calibration")
    with svc.db.session() as s:
        _session(s, session_id)
        rec = s.get(TargetCalibrationRecord, cal_id)
    if rec is None or rec.session_id != session_id:
        raise Problem(404, "not-found", f"calibration {cal_id!r} is not in {session_id}")
    return rec


@router.get("/target-sessions/{session_id}/calibrations/{cal_id}",
            response_model=TargetCalibration)
def read_calibration(session_id: str, cal_id: str, svc: Svc) -> dict[str, Any]:
    """A calibration with its statistics (outliers per view, bow, cross-validation)."""
    return _cal_dict(_calibration(svc, session_id, cal_id))


@router.get("/target-sessions/{session_id}/calibrations/{cal_id}/model.json",
            response_class=Response, responses={200: {"content": {"application/json": {}}}})
def download_model(session_id: str, cal_id: str, svc: Svc) -> FileResponse:
    """The fitted model (`phasecal.model/1`)."""
    _calibration(svc, session_id, cal_id)
    return FileResponse(svc.store.file(cal_id, "model.json"), media_type="application/json")


@router.get("/target-sessions/{session_id}/calibrations/{cal_id}/{name}.png",
            response_class=Response, responses={200: {"content": {"image/png": {}}}})
def download_figure(session_id: str, cal_id: str, name: str, svc: Svc) -> FileResponse:
    """`residuals.png` (residual vectors, map and radial profile) or `uncertainty.png`
    (projection uncertainty and the cross-validation difference over the sensor)."""
    if name not in ("residuals", "uncertainty"):
        raise Problem(404, "not-found", f"{name}.png: expected residuals.png or uncertainty.png")
    _calibration(svc, session_id, cal_id)
    return FileResponse(svc.store.file(cal_id, f"{name}.png"), media_type="image/png")
