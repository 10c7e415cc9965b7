"""Rig calibrations: every camera of a several-camera session's poses fitted jointly (a job),
the rig model it gives (phasecal.rig/1) and its exports (one camera, a camera pair, the
cameras' transforms)."""

from __future__ import annotations

import json
import time
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Query
from fastapi.responses import JSONResponse, Response
from sqlalchemy import select

from api.db import CalibrationRecord, PoseRecord
from api.jobs.rig_calibrations import RigCalibrateJob
from api.pose_path import pose_camera_names
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, accepted, get_session
from api.schemas import RigCalibrationCreate
from api.services import Services, get_services
from api.store import check_id, new_id
from calibration import (
    FILE_NAMES,
    MEDIA_TYPES,
    RIG_FILE_NAMES,
    RIG_MEDIA_TYPES,
    ExportOptions,
    ModelError,
    RigModel,
    RigOptions,
    load_rig,
    model_spec,
    rig_export_bytes,
    split_rig_options,
)

router = APIRouter(tags=["calibrations"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
RigFormat = Literal["opencv-yaml", "ros", "mrcal", "remap", "opencv-fit", "opencv-stereo",
                    "stereo-remap", "ros-transforms"]
INFO_HEADER = "Phasecal-Export-Info"
# The rig export routes' query parameters and answer, alike for every kind of rig calibration.
ExportCamera = Annotated[str | None, Query(max_length=64,
                                           description="single-camera formats: the camera")]
ExportPair = Annotated[str | None, Query(max_length=130, description="opencv-stereo, "
                                         "stereo-remap: the pair A,B (X2 = R X1 + T)")]
ExportApproximate = Annotated[bool, Query(description="mrcal: spline fit of a fisheye")]
RIG_EXPORT_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"content": {"application/x-yaml": {}, "text/plain": {}, "application/octet-stream": {}},
          "description": f"the file; {INFO_HEADER}: JSON"}}


def check_rig_options(options: dict[str, Any], models: dict[str, str]) -> None:
    """The joint fit's options and every camera model's options, or a 422 naming the key."""
    rig_opts, model_opts = split_rig_options(options)
    try:
        RigOptions.model_validate(rig_opts)
        for name in sorted(set(models.values())):
            model_spec(name).parse_options(model_opts)
    except ValueError as exc:  # pydantic's ValidationError included
        raise Problem(422, "validation-error", f"options: {exc}".splitlines()[0],
                      field="options") from None


def _pose_cameras(svc: Services, s: Any, session_id: str, ids: list[str], field: str
                  ) -> dict[str, list[str]]:
    """pose id -> its cameras (reference first); 422/409 for poses the fit cannot use."""
    out = {}
    for pid in ids:
        check_id(pid, "pose", "pose")
        p = s.get(PoseRecord, pid)
        if p is None or p.session_id != session_id:
            raise Problem(422, "validation-error",
                          f"{field}: pose {pid!r} is not a pose of session {session_id}",
                          field=field)
        if p.status not in ("ready", "flagged"):
            raise Problem(409, "not-ready", f"{field}: pose {pid} is {p.status}, not ready")
        cams = pose_camera_names(svc.store.dir_for(pid))
        if not cams:
            raise Problem(422, "validation-error",
                          f"{field}: pose {pid} has one camera; calibrate one camera with "
                          f"POST /sessions/{session_id}/calibrations", field=field)
        out[pid] = cams
    return out


@router.post("/sessions/{session_id}/rig-calibrations", status_code=202, response_model=None,
             responses={202: {"description": "rig calibration job accepted; Location: /jobs/<id>"}})
def create_rig_calibration(session_id: str, body: RigCalibrationCreate, svc: Svc
                           ) -> JSONResponse:
    """Fit every camera of the chosen poses (default: every ready pose not held out) jointly."""
    cid = new_id("cal")
    held = list(dict.fromkeys(body.heldout_pose_ids))
    with svc.db.claim_session() as s:
        get_session(s, session_id)
        if body.pose_ids is None:
            ready = s.scalars(select(PoseRecord.id).where(PoseRecord.session_id == session_id,
                                                          PoseRecord.status == "ready")
                              .order_by(PoseRecord.index))
            pose_ids = [p for p in ready if p not in held]
        else:
            pose_ids = list(dict.fromkeys(body.pose_ids))
        if not pose_ids:
            raise Problem(409, "no-poses", f"session {session_id} has no ready poses to calibrate")
        overlap = sorted(set(pose_ids) & set(held))
        if overlap:
            raise Problem(422, "validation-error",
                          f"heldout_pose_ids: {overlap[0]} is also in pose_ids",
                          field="heldout_pose_ids")
        cams = _pose_cameras(svc, s, session_id, pose_ids, "pose_ids")
        _pose_cameras(svc, s, session_id, held, "heldout_pose_ids")
        cameras = list(dict.fromkeys(c for pid in pose_ids for c in cams[pid]))
        unknown = sorted(set(body.camera_models) - set(cameras))
        if unknown:
            raise Problem(422, "validation-error", f"camera_models: {unknown} are not cameras "
                          f"of these poses ({cameras})", field="camera_models")
        if body.reference is not None and body.reference not in cameras:
            raise Problem(422, "validation-error", f"reference: expected one of {cameras}, got "
                          f"{body.reference!r}", field="reference")
        models = {c: body.camera_models.get(c, body.model) for c in cameras}
        for cam, name in models.items():
            need, got = model_spec(name).min_poses, sum(cam in cams[p] for p in pose_ids)
            if got < need:
                raise Problem(422, "validation-error", f"pose_ids: camera {cam} ({name}) needs "
                              f">= {need} training poses, got {got}", field="pose_ids")
        check_rig_options(body.options, models)
        job = RigCalibrateJob(svc=svc, session_id=session_id, cal_id=cid, models=models,
                              pose_ids=pose_ids, heldout_pose_ids=held, options=body.options,
                              reference=body.reference)
        state = svc.jobs.create(s, job)
        s.add(CalibrationRecord(
            id=cid, session_id=session_id, model=body.model, pose_ids=pose_ids,
            heldout_pose_ids=held, status="queued", job_id=state.id, exports=[],
            options={"rig": {"camera_models": models, "reference": body.reference,
                             "options": body.options}}, created_at=time.time()))
    return accepted(svc.jobs.start(state.id, job))


def _fitted_rig(svc: Services, cal_id: str) -> RigModel:
    """The rig model of a succeeded rig calibration, or a 404/409 problem saying why not."""
    check_id(cal_id, "cal", "calibration")
    with svc.db.session() as s:
        rec = s.get(CalibrationRecord, cal_id)
        if rec is None:
            raise Problem(404, "not-found", f"calibration {cal_id!r} does not exist")
        status, rig_cal = rec.status, "rig" in (rec.options or {})
    if not rig_cal:
        raise Problem(404, "not-found", f"calibration {cal_id} is of one camera, not a rig "
                      f"(its model: /calibrations/{cal_id}/model.json)")
    if status != "succeeded":
        raise Problem(409, "not-ready", f"calibration {cal_id} is {status}; the rig model "
                      "exists once it succeeded")
    return load_rig(svc.store.file(cal_id, "rig.json"))


@router.get("/calibrations/{cal_id}/rig", response_model=None)
def read_rig(cal_id: str, svc: Svc) -> JSONResponse:
    """The rig model (phasecal.rig/1): each camera's model and extrinsics with covariance."""
    return JSONResponse(_fitted_rig(svc, cal_id).to_dict())


@router.get("/calibrations/{cal_id}/rig/export", response_class=Response,
            responses=RIG_EXPORT_RESPONSES)
def export_rig(
    cal_id: str, svc: Svc, format: RigFormat, camera: ExportCamera = None,
    cameras: ExportPair = None, approximate: ExportApproximate = False,
) -> Response:
    """One camera in a single-camera format (mrcal with its extrinsics), a camera pair as
    opencv-stereo or stereo-remap, or every camera's pose as ROS transforms."""
    return rig_export_response(_fitted_rig(svc, cal_id), cal_id, format, camera, cameras,
                               approximate)


def rig_export_response(rig: Any, cal_id: str, format: str, camera: str | None,
                        cameras: str | None, approximate: bool) -> Response:
    """A fitted rig's export as the export routes answer it (422 for a bad pair or a format
    the rig's models cannot carry)."""
    pair = None
    if cameras is not None:
        names = [c.strip() for c in cameras.split(",")]
        if len(names) != 2 or not all(names):
            raise Problem(422, "validation-error", f"cameras: expected A,B, got {cameras!r}",
                          field="cameras")
        pair = (names[0], names[1])
    try:
        data, info = rig_export_bytes(rig, format, camera=camera, cameras=pair,
                                      opts=ExportOptions(approximate=approximate))
    except ModelError as exc:
        raise Problem(422, "export-refused", f"format {format}: {exc}") from None
    name = RIG_FILE_NAMES.get(format) or f"{camera}-{FILE_NAMES[format]}"
    media = RIG_MEDIA_TYPES.get(format) or MEDIA_TYPES[format]
    return Response(data, media_type=media, headers={
        "Content-Disposition": f'attachment; filename="{cal_id}-{name}"',
        INFO_HEADER: json.dumps(info, separators=(",", ":"))})
