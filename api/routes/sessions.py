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

from api.capture import capture_frames, stored_indices
from api.db import PoseRecord, SessionRecord
from api.frames_upload import store_images, store_npy
from api.maps_upload import validated_maps
from api.previews import PREVIEW_KINDS, preview_png
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, accepted, get_pose, get_session, pose_to_dict
from api.schemas import MAX_OFFSET, CaptureRequest, Pose, Session, SessionCreate
from api.services import Services, get_services
from api.store import check_id, new_id
from calibration.maps import load_maps
from calibration.plan import Plan, plan_from_dict
from calibration.progress import TaskContext
from calibration.worker.tasks import decode_task, stream_decode_task

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
    rig_id = body.rig_id or svc.rigs.default_id
    check_id(rig_id, "rig", "rig")
    svc.rigs.record(rig_id)
    if body.plan is not None:
        if body.preset is not None:
            raise Problem(422, "validation-error", "give either plan or preset, not both")
        plan = plan_from_dict(body.plan, "plan")
    else:
        from acquisition.patterns import build_plan

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


def _new_pose(svc: Services, session_id: str, source: str, kind: str,
              screen_pose: dict[str, Any] | None) -> tuple[str, dict[str, Any]]:
    """Insert a pose and its queued job in one transaction."""
    pid = new_id("pose")
    with svc.db.claim_session() as s:
        get_session(s, session_id)
        index = _next_index(s, session_id)
        job = svc.jobs.create(s, kind, f"/sessions/{session_id}/poses/{pid}", session_id,
                              claims=(pid,))
        s.add(PoseRecord(id=pid, session_id=session_id, index=int(index), source=source,
                         status="pending", job_id=job.id, frames_done=0,
                         screen_pose=screen_pose, created_at=time.time()))
    return pid, svc.jobs.get(job.id) or {}


def _next_index(s: Any, session_id: str) -> int:
    """The next pose index of a session (after the highest: poses can be deleted)."""
    last = s.scalar(select(func.max(PoseRecord.index)).where(PoseRecord.session_id == session_id))
    return 0 if last is None else int(last) + 1


def _pose_hooks(pose_id: str, frames: Path | None = None) -> tuple[Any, Any]:
    """Success and failure hooks of a pose's job; `frames`: the pose folder, whose stored
    frames are the pose's progress when the job stops early."""

    def ok(s: Any, result: dict[str, Any]) -> None:
        p = s.get(PoseRecord, pose_id)
        dec = result.get("decode", {})
        flagged = result.get("capture", {}).get("flagged")
        # a pose that failed its integrity check keeps its maps but is not used by default
        if flagged:
            p.status, p.error = "flagged", f"integrity check: {flagged}"
        else:
            p.status, p.error = "ready", None
        p.valid_pixels = dec.get("valid_pixels")
        p.width, p.height = dec.get("width"), dec.get("height")
        p.frames_done = result.get("frames", p.frames_done)

    def fail(s: Any, status: str, error: str) -> None:
        p = s.get(PoseRecord, pose_id)
        p.status = status if status in ("cancelled", "interrupted") else "failed"
        p.error = error
        if frames is not None:
            p.frames_done = len(stored_indices(frames))

    return ok, fail


def _set_pose_status(svc: Services, pose_id: str, status: str) -> None:
    with svc.db.session() as s:
        s.get(PoseRecord, pose_id).status = status


def _decode(svc: Services, ctx: TaskContext, session_dir: Path, frames: Path, pose_dir: Path,
            meta: dict[str, Any], noise: Any) -> dict[str, Any]:
    """Run the decode task on the executor and wait for it (cancel propagates).

    The worker writes into the job's staging folder; only this server moves the maps into
    the pose folder, once the task succeeded.
    """
    with svc.store.staging(ctx.job_id) as staged:
        fut = svc.executor.run_task(decode_task, str(session_dir / "plan.json"), str(frames),
                                    str(staged / "maps.npz"), job_id=ctx.job_id,
                                    on_progress=ctx.progress, noise=noise, meta=meta)
        result = fut.result()
        ctx.check_cancelled()
        svc.store.commit(staged, ["maps.npz"], pose_dir)
    return result


def _start_capture(svc: Services, session_id: str, pose_id: str, rig_id: str, plan: Plan,
                   screen_pose: dict[str, Any] | None, job_id: str,
                   noise_dn: float | None = None) -> None:
    """Capture into the pose's frame store while a worker decodes the stored frames live."""
    session_dir = svc.store.dir_for(session_id)
    pose_dir = svc.store.dir_for(pose_id)

    def body(ctx: TaskContext) -> dict[str, Any]:
        handle = svc.rigs.handle(rig_id)
        ctx.progress(0, len(plan.frames), "waiting for rig")
        meta = {"pose_id": pose_id, "session_id": session_id, "plan_digest": plan.digest(),
                "camera": handle.rig.camera.info.name}
        with svc.store.staging(ctx.job_id) as staged:
            with handle.lock:
                ctx.check_cancelled()
                _set_pose_status(svc, pose_id, "capturing")
                if screen_pose is not None:
                    _move_screen(handle, screen_pose)
                # simulated rigs decode like real ones: the noise is the client's noise_dn
                # or is estimated from the residuals (the simulator's model is ground truth)
                fut = svc.executor.run_task(
                    stream_decode_task, str(session_dir / "plan.json"), str(pose_dir),
                    str(staged / "maps.npz"), job_id=ctx.job_id, on_progress=ctx.progress,
                    noise=noise_dn, meta=meta)
                try:
                    cap = capture_frames(ctx, handle.rig, plan, pose_dir,
                                         on_frame=svc.preview.publisher(rig_id))
                except BaseException:
                    svc.executor.cancel(ctx.job_id)  # the worker stops following the store
                    raise
                finally:
                    svc.preview.capture_ended(rig_id)
            _set_pose_status(svc, pose_id, "decoding")
            dec = fut.result()
            ctx.check_cancelled()
            decoded_at = time.time()
            svc.store.commit(staged, ["maps.npz"], pose_dir)
            dec["commit_s"] = round(time.time() - decoded_at, 4)
        return {"capture": cap, "decode": dec, "frames": len(stored_indices(pose_dir))}

    ok, fail = _pose_hooks(pose_id, pose_dir)
    svc.jobs.start(job_id, body, ok, fail)


def _move_screen(handle: Any, screen_pose: dict[str, Any]) -> None:
    """Place the simulated screen (409 on a real rig, where a person or robot moves it)."""
    sim = handle.simulated
    if sim is None:
        raise Problem(409, "not-simulated", f"rig {handle.rig_id} is not simulated: move the "
                      "screen physically and capture without screen_pose")
    import cv2
    import numpy as np

    rot, _ = cv2.Rodrigues(np.asarray(screen_pose["rvec"], np.float64))
    sim.set_pose(rot, np.asarray(screen_pose["tvec_mm"], np.float64))




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
    if screen_pose is not None and svc.rigs.handle(rig_id).simulated is None:
        raise Problem(409, "not-simulated",
                      f"rig {rig_id} is not simulated: screen_pose moves only a simulated screen")
    plan = plan_from_dict(plan_data, f"session {session_id} plan")
    pid, job = _new_pose(svc, session_id, "capture", "capture", screen_pose)
    _start_capture(svc, session_id, pid, rig_id, plan, screen_pose, job["id"],
                   body.noise_dn if body else None)
    return accepted(job)


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
        job = svc.jobs.create(s, "capture", f"/sessions/{session_id}/poses/{pose_id}",
                              session_id, claims=(pose_id,))
        pose.job_id, pose.status, pose.error = job.id, "pending", None
        rig_id, plan_data, screen_pose = sess.rig_id, sess.plan, pose.screen_pose
    plan = plan_from_dict(plan_data, f"session {session_id} plan")
    _start_capture(svc, session_id, pose_id, rig_id or "", plan, screen_pose, job.id)
    return accepted(svc.jobs.get(job.id) or {})


@router.post("/sessions/{session_id}/poses/import", status_code=202, response_model=None,
             openapi_extra={"x-upload": "one .npy (F,H,W) or frame_NNNN.png/.tif images"})
def import_pose(session_id: str, svc: Svc, files: Annotated[list[UploadFile], File()],
                noise_dn: Annotated[float | None, Form(gt=0, le=1e4)] = None) -> JSONResponse:
    """Import frames captured elsewhere (FORMATS.md) as a new pose and decode them (a job)."""
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
        pid, job = _new_pose(svc, session_id, "import", "decode", None)
        pose_dir = svc.store.dir_for(pid)
        svc.store.replace_dir(scratch / frames_name, pose_dir / frames_name)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    session_dir = svc.store.dir_for(session_id)
    meta = {"pose_id": pid, "session_id": session_id, "plan_digest": plan.digest(),
            "camera": "imported"}

    def body(ctx: TaskContext) -> dict[str, Any]:
        _set_pose_status(svc, pid, "decoding")
        dec = _decode(svc, ctx, session_dir, pose_dir / frames_name, pose_dir, meta, noise_dn)
        return {"decode": dec, "frames": len(plan.frames), "shape": [h, w]}

    ok, fail = _pose_hooks(pid)
    svc.jobs.start(job["id"], body, ok, fail)
    return accepted(job)


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
    svc.store.write_bytes(svc.store.file(pid, "maps.npz"), data)
    h, w = maps.shape
    with svc.db.session() as s:
        get_session(s, session_id)
        index = _next_index(s, session_id)
        rec = PoseRecord(id=pid, session_id=session_id, index=int(index), source="import",
                         status="ready", job_id=None, valid_pixels=maps.valid_count(), width=w,
                         height=h, frames_done=0, created_at=time.time())
        s.add(rec)
    return JSONResponse(pose_to_dict(rec), status_code=201,
                        headers={"Location": f"/sessions/{session_id}/poses/{pid}"})


@router.get("/sessions/{session_id}/poses", response_model=list[Pose])
def list_poses(session_id: str, svc: Svc) -> list[dict[str, Any]]:
    """The session's poses in capture order."""
    with svc.db.session() as s:
        get_session(s, session_id)
        recs = s.scalars(select(PoseRecord).where(PoseRecord.session_id == session_id)
                         .order_by(PoseRecord.index)).all()
        return [pose_to_dict(p) for p in recs]


@router.get("/sessions/{session_id}/poses/{pose_id}", response_model=Pose)
def read_pose(session_id: str, pose_id: str, svc: Svc) -> dict[str, Any]:
    """One pose."""
    with svc.db.session() as s:
        return pose_to_dict(get_pose(s, session_id, pose_id))


def _ready_maps_path(svc: Services, session_id: str, pose_id: str) -> Path:
    with svc.db.session() as s:
        pose = get_pose(s, session_id, pose_id)
        if pose.status not in ("ready", "flagged"):
            raise Problem(409, "not-ready", f"pose {pose_id} is {pose.status}; maps exist once "
                          "it is ready")
    return svc.store.file(pose_id, "maps.npz")


@router.get("/sessions/{session_id}/poses/{pose_id}/maps.npz", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}}}})
def download_maps(session_id: str, pose_id: str, svc: Svc) -> Response:
    """Decoded maps (phasecal.maps/1 NPZ)."""
    path = _ready_maps_path(svc, session_id, pose_id)
    return Response(path.read_bytes(), media_type="application/octet-stream",
                    headers={"Content-Disposition": f'attachment; filename="{pose_id}.npz"'})


@router.get("/sessions/{session_id}/poses/{pose_id}/preview/{kind}.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}})
def preview(session_id: str, pose_id: str, kind: str, svc: Svc) -> Response:
    """PNG preview of the x, y, sigma or mask map."""
    if kind not in PREVIEW_KINDS:
        raise Problem(404, "not-found", f"preview {kind!r}: expected one of {list(PREVIEW_KINDS)}")
    maps = load_maps(_ready_maps_path(svc, session_id, pose_id))
    return Response(preview_png(maps, kind), media_type="image/png")
