"""Rig calibrations from target sessions: one target session per camera (each its own image
size, the same board), views paired across cameras by shot name, every camera fitted jointly
as a job; the rig model (phasecal.rig/1), its exports and its report page as a screen
session's rig offers."""

from __future__ import annotations

import time
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query
from fastapi.responses import HTMLResponse, JSONResponse, Response
from pydantic import BaseModel, Field

from api.db import TargetRigCalibrationRecord, TargetSessionRecord, TargetViewRecord
from api.jobs.target_rig import TargetRigCalibrateJob, target_rig_report_folder
from api.problems import Problem
from api.reports import drawing_page
from api.routes.common import (
    PROBLEM_RESPONSES,
    accepted,
    check_report_file,
    report_file_response,
    report_page_response,
)
from api.routes.rig_calibrations import (
    RIG_EXPORT_RESPONSES,
    ExportApproximate,
    ExportCamera,
    ExportPair,
    RigFormat,
    check_rig_options,
    rig_export_response,
)
from api.schemas import IdStr, ModelName, strict_config
from api.services import Services, get_services
from api.store import check_id, new_id
from calibration import (
    RigModel,
    check_connected,
    load_rig,
    model_spec,
    observation_refusal,
)

router = APIRouter(tags=["target sessions"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
MAX_SHOTS = 2000


class TargetRigCamera(BaseModel):
    """One camera of the rig: its target session and its views, each named by its shot."""

    model_config = strict_config()
    session_id: IdStr
    views: dict[IdStr, IdStr] = Field(max_length=MAX_SHOTS, description=(
        "shot name -> view id of this session; views of one shot name are one board "
        "placement the cameras saw at once"))


class TargetRigCalibrationCreate(BaseModel):
    """Calibrate several cameras jointly from board observations (docs/rigs.md)."""

    model_config = strict_config({
        "cameras": {"left": {"session_id": "ses_…", "views": {"shot1": "pose_…"}},
                    "right": {"session_id": "ses_…", "views": {"shot1": "pose_…"}}},
        "reference": "left", "model": "opencv5", "camera_models": {"right": "sgcc"},
        "heldout_shots": []})
    cameras: dict[IdStr, TargetRigCamera] = Field(max_length=64)
    reference: IdStr | None = Field(default=None, description="default: the first camera")
    model: ModelName = Field(description="every camera's model unless camera_models names one")
    camera_models: dict[IdStr, ModelName] = Field(default_factory=dict, max_length=64)
    heldout_shots: list[IdStr] = Field(default_factory=list, max_length=MAX_SHOTS)
    options: dict[IdStr, Any] = Field(
        default_factory=dict, max_length=64,
        description="the joint fit's options (max_points_per_view, outlier_sigmas, "
                    "max_iterations, seed) and every camera's model options")


class TargetRigCalibration(BaseModel):
    """A rig calibration from target sessions: its inputs, status and statistics."""

    id: str
    cameras: dict[str, Any]
    reference: str
    camera_models: dict[str, str]
    heldout_shots: list[str]
    options: dict[str, Any]
    status: str
    job_id: str | None
    stats: dict[str, Any] | None
    error: str | None
    created_at: float


def _invalid(field: str, detail: str) -> Problem:
    return Problem(422, "validation-error", f"{field}: {detail}", field=field)


def _check_sessions(s: Any, body: TargetRigCalibrationCreate) -> None:
    """Every camera's session exists, is no other camera's, holds its views and shows the
    same target as the others; 422 naming the field otherwise."""
    owner: dict[str, str] = {}
    targets: dict[str, str] = {}
    for cam, spec in body.cameras.items():
        field = f"cameras.{cam}.session_id"
        rec = s.get(TargetSessionRecord, spec.session_id)
        if rec is None:
            raise _invalid(field, f"target session {spec.session_id!r} does not exist")
        if spec.session_id in owner:
            raise _invalid(field, f"target session {spec.session_id} is also camera "
                           f"{owner[spec.session_id]}'s; each camera has its own session")
        owner[spec.session_id] = cam
        targets[cam] = rec.target
        if len(set(spec.views.values())) != len(spec.views):
            raise _invalid(f"cameras.{cam}.views", "a view is named by two shots")
        for shot, vid in spec.views.items():
            view = s.get(TargetViewRecord, vid)
            if view is None or view.session_id != spec.session_id:
                raise _invalid(f"cameras.{cam}.views.{shot}",
                               f"view {vid!r} is not a view of target session {spec.session_id}")
    first = next(iter(targets))
    for cam, target in targets.items():
        if target != targets[first]:
            raise _invalid(f"cameras.{cam}.session_id", f"its target {target!r} is not camera "
                           f"{first}'s {targets[first]!r}; a rig's cameras see one board")


def _check_fit(body: TargetRigCalibrationCreate, models: dict[str, str]) -> None:
    """Shots, models and options the joint fit can use; 422 naming the field otherwise."""
    shots = {shot for spec in body.cameras.values() for shot in spec.views}
    unknown = sorted(set(body.heldout_shots) - shots)
    if unknown:
        raise _invalid("heldout_shots", f"{unknown[:5]} are no camera's shots")
    held = set(body.heldout_shots)
    training = {cam: set(spec.views) - held for cam, spec in body.cameras.items()}
    for cam, name in models.items():
        need, got = model_spec(name).min_poses, len(training[cam])
        if got < need:
            raise _invalid(f"cameras.{cam}.views", f"camera {cam} ({name}) needs >= {need} "
                           f"training views, got {got}")
    try:
        check_connected(training)
    except ValueError as exc:
        raise _invalid("cameras", str(exc).removeprefix("cameras: ")) from None
    for cam, name in models.items():  # every camera of a target rig is fitted to observations
        refusal = observation_refusal(name)
        if refusal is not None:
            raise _invalid(f"camera_models.{cam}" if cam in body.camera_models else "model",
                           refusal)
    check_rig_options(body.options, models)


@router.post("/target-rig-calibrations", status_code=202, response_model=None,
             responses={202: {"description": "rig calibration job accepted; Location: /jobs/<id>"}})
def create_target_rig_calibration(body: TargetRigCalibrationCreate, svc: Svc) -> JSONResponse:
    """Fit every camera's board observations jointly: one target session per camera, views
    of one shot name seen at once; the result is a rig model (phasecal.rig/1)."""
    cameras = list(body.cameras)
    if len(cameras) < 2:
        raise _invalid("cameras", f"a rig needs >= 2 cameras, got {len(cameras)}; calibrate "
                       "one camera with POST /target-sessions/{id}/calibrations")
    unknown = sorted(set(body.camera_models) - set(cameras))
    if unknown:
        raise _invalid("camera_models", f"{unknown} are not cameras of this rig ({cameras})")
    reference = body.reference or cameras[0]
    if reference not in cameras:
        raise _invalid("reference", f"expected one of {cameras}, got {reference!r}")
    models = {c: body.camera_models.get(c, body.model) for c in cameras}
    _check_fit(body, models)
    spec = {cam: c.model_dump() for cam, c in body.cameras.items()}
    held = list(dict.fromkeys(body.heldout_shots))
    cid = new_id("cal")
    with svc.db.claim_session() as s:
        _check_sessions(s, body)
        job = TargetRigCalibrateJob(svc=svc, cal_id=cid, cameras=spec, models=models,
                                    heldout_shots=held, options=body.options,
                                    reference=reference)
        state = svc.jobs.create(s, job)
        s.add(TargetRigCalibrationRecord(
            id=cid, cameras=spec, heldout_shots=held, reference=reference,
            camera_models=models, options=body.options, status="queued", job_id=state.id,
            created_at=time.time()))
    return accepted(svc.jobs.start(state.id, job))


def _record(svc: Services, cal_id: str) -> TargetRigCalibrationRecord:
    check_id(cal_id, "cal", "calibration")
    with svc.db.session() as s:
        rec = s.get(TargetRigCalibrationRecord, cal_id)
    if rec is None:
        raise Problem(404, "not-found", f"target rig calibration {cal_id!r} does not exist")
    return rec


def _fitted_rig(svc: Services, cal_id: str) -> RigModel:
    """The rig model of a succeeded calibration, or a 404/409 problem saying why not."""
    rec = _record(svc, cal_id)
    if rec.status != "succeeded":
        raise Problem(409, "not-ready", f"calibration {cal_id} is {rec.status}; the rig model "
                      "exists once it succeeded")
    return load_rig(svc.store.file(cal_id, "rig.json"))


@router.get("/target-rig-calibrations/{cal_id}", response_model=TargetRigCalibration)
def read_target_rig_calibration(cal_id: str, svc: Svc) -> dict[str, Any]:
    """The calibration: cameras, shots, status and (once it succeeded) the fit's summary:
    each camera's extrinsics with their sigma, reduced chi2, held-out shots' scores."""
    rec = _record(svc, cal_id)
    return {k: getattr(rec, k) for k in TargetRigCalibration.model_fields}


@router.get("/target-rig-calibrations/{cal_id}/rig", response_model=None)
def read_target_rig(cal_id: str, svc: Svc) -> JSONResponse:
    """The rig model (phasecal.rig/1): each camera's model and extrinsics with covariance."""
    return JSONResponse(_fitted_rig(svc, cal_id).to_dict())


@router.get("/target-rig-calibrations/{cal_id}/rig/export", response_class=Response,
            responses=RIG_EXPORT_RESPONSES)
def export_target_rig(
    cal_id: str, svc: Svc, format: RigFormat, camera: ExportCamera = None,
    cameras: ExportPair = None, approximate: ExportApproximate = False,
) -> Response:
    """One camera in a single-camera format, a camera pair as opencv-stereo or stereo-remap,
    or every camera's pose as ROS transforms (as /calibrations/{id}/rig/export)."""
    return rig_export_response(_fitted_rig(svc, cal_id), cal_id, format, camera, cameras,
                               approximate)


@router.get("/target-rig-calibrations/{cal_id}/report.html", response_class=HTMLResponse,
            responses={202: {"content": {"text/html": {}},
                             "description": "the fit is still running: a page that says so "
                                            "and reloads itself"}})
def target_rig_report_page(cal_id: str, svc: Svc, download: Annotated[bool, Query(
        description="the report as one self-contained file (images inlined) to save")] = False,
                           ) -> HTMLResponse:
    """The rig's report: every camera (model, key numbers, joint-fit RMS, views, coverage of
    its sensor by the detected board points), the extrinsics with their 1-sigma, a verdict
    against stated thresholds, held-out shots and the rig's downloads. Drawn by the job;
    while the fit runs (202) a page that says so and reloads itself."""
    rec = _record(svc, cal_id)
    folder = target_rig_report_folder(svc, rec)
    if folder is None:
        return HTMLResponse(drawing_page(cal_id, rec.status),
                            status_code=202, headers={"Retry-After": "2"})
    page = (folder / "report.html").read_text(encoding="utf-8")
    return report_page_response(cal_id, folder, page, download)


@router.get("/target-rig-calibrations/{cal_id}/report/{name}", response_class=Response,
            responses={200: {"content": {"image/png": {}, "text/html": {}}}})
def target_rig_report_file(cal_id: str, name: str, svc: Svc) -> Response:
    """One PNG of the report (names as linked from report.html), or report.html itself."""
    check_report_file(name)
    folder = target_rig_report_folder(svc, _record(svc, cal_id))
    if folder is None:
        raise Problem(409, "not-ready", f"calibration {cal_id}'s report is drawn once its fit "
                      "has succeeded; ask again in a few seconds")
    return report_file_response(cal_id, name, folder)
