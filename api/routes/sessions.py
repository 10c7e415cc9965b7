"""Sessions and poses: create a session, capture/import/resume poses, maps and previews."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends, File, Form, Query, UploadFile
from fastapi.responses import JSONResponse, Response
from sqlalchemy import func, select

from acquisition.patterns import build_plan
from api.db import PoseRecord, SessionRecord
from api.frames_upload import store_images, store_npy
from api.jobs.poses import CaptureJob, ImportDecodeJob, PoseJob
from api.maps_upload import validated_maps
from api.pose_path import camera_maps_path
from api.previews import PREVIEW_KINDS, preview_png
from api.problems import Problem
from api.routes.common import (
    PROBLEM_RESPONSES,
    CameraQuery,
    accepted,
    get_pose,
    get_session,
    pose_to_dict,
)
from api.schemas import MAX_OFFSET, CaptureRequest, Pose, Session, SessionCreate
from api.services import Services, get_services
from api.store import new_id
from calibration.shared.maps import load_maps
from calibration.shared.plan import plan_from_dict

router = APIRouter(tags=["sessions"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]


def _session_dict(rec: SessionRecord) -> dict[str, Any]:
    plan = plan_from_dict(rec.plan, f"session {rec.id} plan")
    return {"id": rec.id, "name": rec.name, "rig_id": rec.rig_id,
            "frame_count": len(plan.frames), "plan_digest": plan.digest(),
            "created_at": rec.created_at}


@router.post("/sessions", status_code=201, response_model=Session)
def create_session(body: SessionCreate, svc: Svc) -> JSONResponse:
    """Create a session on a rig with a plan (given, or from a preset for the rig's screen)."""
    rig_id = svc.rigs.resolve(body.rig_id or "default")
    svc.rigs.record(rig_id)
    if body.plan is not None:
        if body.preset is not None:
            raise Problem(422, "validation-error", "give either plan or preset, not both")
        plan = plan_from_dict(body.plan, "plan")
    else:

        screen = svc.rigs.handle(rig_id).rig.screen
        plan = build_plan(screen.width_px, screen.height_px, list(screen.pitch_mm),
                          preset=body.preset or "default")
    sid = new_id("ses")
    folder = svc.store.dir_for(sid)
    svc.store.write_bytes(folder / "plan.json", json.dumps(plan.to_dict(), indent=1).encode())
    with svc.db.session() as s:
        rec = SessionRecord(id=sid, rig_id=rig_id, name=body.name, plan=plan.to_dict(),
                            created_at=time.time())
        s.add(rec)
    return JSONResponse(_session_dict(rec), status_code=201,
                        headers={"Location": f"/sessions/{sid}"})


@router.get("/sessions", response_model=list[Session])
def list_sessions(svc: Svc, limit: Annotated[int, Query(ge=1, le=500)] = 100,
                  offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0) -> list[dict[str, Any]]:
    """Sessions, newest first."""
    with svc.db.session() as s:
        recs = s.scalars(select(SessionRecord).order_by(SessionRecord.created_at.desc())
                         .limit(limit).offset(offset)).all()
        return [_session_dict(r) for r in recs]


@router.get("/sessions/{session_id}", response_model=Session)
def read_session(session_id: str, svc: Svc) -> dict[str, Any]:
    """One session."""
    with svc.db.session() as s:
        return _session_dict(get_session(s, session_id))


@router.get("/sessions/{session_id}/plan")
def read_plan(session_id: str, svc: Svc) -> dict[str, Any]:
    """The session's pattern plan (phasecal.plan/1)."""
    with svc.db.session() as s:
        return get_session(s, session_id).plan


def _next_index(s: Any, session_id: str) -> int:
    """The next pose index of a session (after the highest: poses can be deleted)."""
    last = s.scalar(select(func.max(PoseRecord.index)).where(PoseRecord.session_id == session_id))
    return 0 if last is None else int(last) + 1


def _add_pose(s: Any, svc: Services, job: PoseJob, source: str,
              screen_pose: dict[str, Any] | None) -> str:
    """Insert the pose and its queued job in one transaction; the job's id."""
    get_session(s, job.session_id or "")
    index = _next_index(s, job.session_id or "")
    state = svc.jobs.create(s, job)
    s.add(PoseRecord(id=job.pose_id, session_id=job.session_id, index=int(index),
                     source=source, status="pending", job_id=state.id, frames_done=0,
                     screen_pose=screen_pose, created_at=time.time()))
    return state.id


@router.post("/sessions/{session_id}/poses", status_code=202, response_model=None,
             responses={202: {"description": "capture job accepted; Location: /jobs/<id>"}})
def capture_pose(session_id: str, svc: Svc, body: CaptureRequest | None = None) -> JSONResponse:
    """Capture a new pose on the session's rig (a job); optionally move the simulated screen."""
    with svc.db.session() as s:
        sess = get_session(s, session_id)
        rig_id, plan_data = sess.rig_id, sess.plan
    if rig_id is None:
        raise Problem(409, "no-rig", f"session {session_id} has no rig; import frames instead")
    screen_pose = body.screen_pose.model_dump() if body and body.screen_pose else None
    if screen_pose is not None:
        svc.rigs.handle(rig_id).placeable()  # 409 on hardware, or where the mover holds the view
    job = CaptureJob(svc=svc, session_id=session_id, pose_id=new_id("pose"), rig_id=rig_id,
                     plan=plan_from_dict(plan_data, f"session {session_id} plan"),
                     screen_pose=screen_pose, noise_dn=body.noise_dn if body else None)
    svc.space.require(job.bytes_needed(), f"a capture on rig {rig_id}")
    with svc.db.claim_session() as s:
        job_id = _add_pose(s, svc, job, "capture", screen_pose)
    return accepted(svc.jobs.start(job_id, job))


@router.post("/sessions/{session_id}/poses/{pose_id}/resume", status_code=202, response_model=None)
def resume_pose(session_id: str, pose_id: str, svc: Svc) -> JSONResponse:
    """Resume an interrupted/cancelled/failed capture at the first missing frame (a new job)."""
    with svc.db.claim_session() as s:  # check + claim cannot race with another resume
        pose = get_pose(s, session_id, pose_id)
        sess = get_session(s, session_id)
        if pose.source != "capture":
            raise Problem(409, "conflict", f"pose {pose_id} was imported; import it again instead")
        if pose.status not in ("interrupted", "cancelled", "failed"):
            raise Problem(409, "conflict", f"pose {pose_id} is {pose.status}; only interrupted, "
                          "cancelled or failed captures can be resumed")
        job = CaptureJob(svc=svc, session_id=session_id, pose_id=pose_id,
                         rig_id=sess.rig_id or "",
                         plan=plan_from_dict(sess.plan, f"session {session_id} plan"),
                         screen_pose=pose.screen_pose)
        svc.space.require(job.bytes_needed(), f"resuming pose {pose_id}")
        state = svc.jobs.create(s, job)
        pose.job_id, pose.status, pose.error = state.id, "pending", None
    return accepted(svc.jobs.start(state.id, job))


@router.post("/sessions/{session_id}/poses/import", status_code=202, response_model=None,
             openapi_extra={"x-upload": "one .npy (F,H,W) or frame_NNNN.png/.tif images"})
def import_pose(session_id: str, svc: Svc, files: Annotated[list[UploadFile], File()],
                noise_dn: Annotated[float | None, Form(gt=0, le=1e4)] = None) -> JSONResponse:
    """Import frames captured elsewhere (docs/formats.md, "Captured frames") as a new pose and
    decode them (a job)."""
    with svc.db.session() as s:
        plan = plan_from_dict(get_session(s, session_id).plan, f"session {session_id} plan")
    scratch = svc.store.temp_dir()
    try:
        if len(files) == 1 and (files[0].filename or "").lower().endswith(".npy"):
            frames_name = "frames.npy"
            h, w = store_npy(files[0].file, files[0].filename or "frames.npy", plan,
                             scratch / frames_name)
        else:
            frames_name = "frames"
            h, w = store_images([(f.filename or "", f.file.read()) for f in files], plan,
                                scratch / frames_name)
        pid = new_id("pose")
        pose_dir = svc.store.dir_for(pid, create=False)
        meta = {"pose_id": pid, "session_id": session_id, "plan_digest": plan.digest(),
                "camera": "imported"}
        job = ImportDecodeJob(svc=svc, session_id=session_id, pose_id=pid,
                              frames=pose_dir / frames_name, frame_count=len(plan.frames),
                              meta=meta, shape=(h, w), noise_dn=noise_dn)
        with svc.db.claim_session() as s:
            job_id = _add_pose(s, svc, job, "import", None)
        svc.store.replace_dir(scratch / frames_name, svc.store.dir_for(pid) / frames_name)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return accepted(svc.jobs.start(job_id, job))


@router.post("/sessions/{session_id}/poses/import-maps", status_code=201, response_model=Pose)
def import_maps(session_id: str, svc: Svc, file: Annotated[UploadFile, File()]) -> JSONResponse:
    """Import maps decoded elsewhere (`phasecal decode` NPZ) as a ready pose."""
    with svc.db.session() as s:
        plan = plan_from_dict(get_session(s, session_id).plan, f"session {session_id} plan")
        size = s.execute(select(PoseRecord.width, PoseRecord.height).where(
            PoseRecord.session_id == session_id, PoseRecord.width.is_not(None)).limit(1)).first()
    data = file.file.read()
    maps = validated_maps(data, file.filename or "maps.npz", plan,
                          svc.config.max_upload_bytes, tuple(size) if size else None)
    digest = maps.meta.get("plan_digest")
    if digest is not None and digest != plan.digest():
        raise Problem(422, "frames-plan-mismatch",
                      f"{file.filename}: maps were decoded with plan {digest}, the session's "
                      f"plan is {plan.digest()}")
    pid = new_id("pose")
    h, w = maps.shape
    try:
        svc.store.write_bytes(svc.store.file(pid, "maps.npz"), data)
        with svc.db.session() as s:
            get_session(s, session_id)
            index = _next_index(s, session_id)
            rec = PoseRecord(id=pid, session_id=session_id, index=int(index), source="import",
                             status="ready", job_id=None, valid_pixels=maps.valid_count(),
                             width=w, height=h, frames_done=0, created_at=time.time())
            s.add(rec)
    except BaseException:  # (e.g. a full disk) no folder is left without its record
        shutil.rmtree(svc.store.dir_for(pid, create=False), ignore_errors=True)
        raise
    return JSONResponse(pose_to_dict(rec), status_code=201,
                        headers={"Location": f"/sessions/{session_id}/poses/{pid}"})


@router.get("/sessions/{session_id}/poses", response_model=list[Pose])
def list_poses(session_id: str, svc: Svc) -> list[dict[str, Any]]:
    """The session's poses in capture order."""
    with svc.db.session() as s:
        get_session(s, session_id)
        recs = s.scalars(select(PoseRecord).where(PoseRecord.session_id == session_id)
                         .order_by(PoseRecord.index)).all()
        return [pose_to_dict(p, svc.store.dir_for(p.id, create=False)) for p in recs]


@router.get("/sessions/{session_id}/poses/{pose_id}", response_model=Pose)
def read_pose(session_id: str, pose_id: str, svc: Svc) -> dict[str, Any]:
    """One pose (a several-camera pose lists its cameras and each one's status)."""
    with svc.db.session() as s:
        pose = get_pose(s, session_id, pose_id)
        return pose_to_dict(pose, svc.store.dir_for(pose.id, create=False))


def _ready_maps_path(svc: Services, session_id: str, pose_id: str,
                     camera: str | None = None) -> Path:
    with svc.db.session() as s:
        pose = get_pose(s, session_id, pose_id)
        status = pose.status
    try:
        path = camera_maps_path(svc.store.dir_for(pose_id, create=False), camera)
    except ValueError as exc:
        raise Problem(422, "validation-error", str(exc), field="camera") from None
    if status not in ("ready", "flagged"):
        raise Problem(409, "not-ready", f"pose {pose_id} is {status}; maps exist once "
                      "it is ready")
    return path


@router.get("/sessions/{session_id}/poses/{pose_id}/maps.npz", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}}}})
def download_maps(session_id: str, pose_id: str, svc: Svc,
                  camera: CameraQuery = None) -> Response:
    """Decoded maps (phasecal.maps/1 NPZ); of one camera (`camera`) on a several-camera
    pose."""
    path = _ready_maps_path(svc, session_id, pose_id, camera)
    name = pose_id if camera is None else f"{pose_id}-{camera}"
    return Response(path.read_bytes(), media_type="application/octet-stream",
                    headers={"Content-Disposition": f'attachment; filename="{name}.npz"'})


@router.get("/sessions/{session_id}/poses/{pose_id}/preview/{kind}.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}})
def preview(session_id: str, pose_id: str, kind: str, svc: Svc,
            camera: CameraQuery = None) -> Response:
    """PNG preview of the x, y, sigma or mask map (of one camera on a several-camera pose)."""
    if kind not in PREVIEW_KINDS:
        raise Problem(404, "not-found", f"preview {kind!r}: expected one of {list(PREVIEW_KINDS)}")
    maps = load_maps(_ready_maps_path(svc, session_id, pose_id, camera))
    return Response(preview_png(maps, kind), media_type="image/png")
