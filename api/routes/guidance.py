"""Pose guidance: a starting set of poses, whether the captured poses are varied enough, the
predicted ray uncertainty of a session and the next pose to capture."""

from __future__ import annotations

import hashlib
import json
import shutil
import threading
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, Query
from fastapi.responses import JSONResponse, Response
from sqlalchemy import select

from api.db import PoseRecord, SessionRecord
from api.jobs.intrinsics import RESULT as INTRINSICS_RESULT
from api.problems import Problem
from api.rig_guidance import pose_maps_path, rig_next_pose, rig_picture, rig_plan_dir
from api.routes.common import PROBLEM_RESPONSES, CameraQuery, get_session
from api.services import Services, get_services
from api.worker.guidance_task import guidance_task
from calibration import (
    DEFAULT_MIN_VISIBLE,
    MODELS,
    NominalCamera,
    ObservedPose,
    captured_by,
    count_png,
    nominal_camera,
    observe,
    pose_variety,
    starting_poses,
)
from calibration.shared.maps import load_maps
from calibration.shared.plan import plan_from_dict

router = APIRouter(tags=["guidance"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
Model = Annotated[str, Query(description="parametric model the prediction uses",
                             pattern="^(opencv5|opencv-rational|fisheye)$")]
Hfov = Annotated[float | None, Query(
    ge=5, le=200, description="the camera's nominal horizontal field of view (deg; a pinhole "
    "up to 150), used until the session has quick intrinsics (POST /sessions/{id}/intrinsics)")]
Lens = Annotated[Literal["pinhole", "fisheye"], Query(
    description="the nominal lens: a pinhole, or an equidistant fisheye for a wide-angle lens")]
Visible = Annotated[float, Query(
    ge=0.5, le=1.0, description=f"the least part of the suggested screen inside the image "
    f"(default {DEFAULT_MIN_VISIBLE}): below 1 it may reach past the image's edge, which puts "
    "data in the image's corners (every pixel that sees the screen decodes) and lowers the "
    "worst sigma faster; 1 asks for the whole screen in view")]
PLAN_VERSION = 4  # part of every cache key: a changed planner never serves an older plan
_IMMUTABLE = "private, max-age=31536000, immutable"  # a keyed URL's content never changes
_locks: dict[str, threading.Lock] = {}  # one per cached plan: a plan is computed once, while
_locks_guard = threading.Lock()  # other sessions' (and models') plans go on at the same time


def _plan_lock(final: Path) -> threading.Lock:
    """The lock of one cached plan's folder."""
    with _locks_guard:
        return _locks.setdefault(str(final), threading.Lock())


def _ready_poses(svc: Services, session_id: str) -> tuple[SessionRecord, list[PoseRecord]]:
    """The session and its ready poses in capture order (404 if no such session)."""
    with svc.db.session() as s:
        sess = get_session(s, session_id)
        poses = list(s.scalars(select(PoseRecord).where(
            PoseRecord.session_id == session_id, PoseRecord.status == "ready")
            .order_by(PoseRecord.index)))
        s.expunge_all()
    return sess, poses


def _camera(svc: Services, sess: SessionRecord, poses: list[PoseRecord],
            hfov_deg: float | None, lens: str) -> NominalCamera:
    """The session camera's nominal lens: its quick intrinsics when measured, else the
    given (or default) field of view over a decoded pose's (or the rig camera's) image
    size."""
    size = None
    if poses and poses[0].width and poses[0].height:  # no need to open the rig's devices
        size = (int(poses[0].width), int(poses[0].height))
    elif sess.rig_id is not None:
        info = svc.rigs.handle(sess.rig_id).rig.camera.info
        size = (int(info.width), int(info.height))
    if size is None:
        raise Problem(409, "no-camera", f"session {sess.id} has no rig and no decoded pose: "
                      "the camera's image size is unknown")
    measured = svc.store.dir_for(sess.id) / INTRINSICS_RESULT
    try:
        if hfov_deg is None and measured.is_file():
            k = json.loads(measured.read_text())["camera_matrix"]
            return nominal_camera(size, np.asarray(k), source="the session's quick intrinsics",
                                  fisheye=lens == "fisheye")
        return nominal_camera(size, hfov_deg=hfov_deg, fisheye=lens == "fisheye")
    except ValueError as exc:
        raise Problem(422, "validation-error", str(exc)) from None


def _observed(svc: Services, sess: SessionRecord, poses: list[PoseRecord],
              camera: NominalCamera) -> list[tuple[str, ObservedPose]]:
    """Each ready pose's outline and normal (a few hundred points of its maps: read here,
    no fit), cached per pose and camera matrix."""
    k = camera.model.camera_matrix
    tag = hashlib.sha1(np.round(k, 6).tobytes()).hexdigest()[:12]
    folder = svc.store.dir_for(sess.id) / "guidance" / "poses"
    screen = plan_from_dict(sess.plan).screen
    out = []
    for p in poses:
        cached = folder / f"{p.id}-{tag}.json"
        if cached.is_file():
            out.append((p.id, ObservedPose.from_json(json.loads(cached.read_text()))))
            continue
        try:
            seen = observe(load_maps(pose_maps_path(svc, p.id)), screen, k)
        except ValueError:
            continue  # too few valid points to tell: neither a repeat nor variety
        folder.mkdir(parents=True, exist_ok=True)
        svc.store.write_bytes(cached, json.dumps(seen.to_json()).encode())
        out.append((p.id, seen))
    return out


def _variety(svc: Services, session_id: str, hfov_deg: float | None,
             lens: str = "pinhole") -> dict[str, Any]:
    sess, poses = _ready_poses(svc, session_id)
    camera = _camera(svc, sess, poses, hfov_deg, lens) if poses else None
    observed = _observed(svc, sess, poses, camera) if camera else []
    size = camera.model.image_size if camera else (1, 1)
    return pose_variety(observed, size, {m: s.min_poses for m, s in MODELS.items()})


def _guidance_dir(svc: Services, session_id: str, model: str,
                  min_visible: float) -> tuple[Path, str]:
    """Cached guidance for the session's current ready poses and its cache key, computed on
    first request by the executor's worker (the fit takes seconds of CPU; the server paces
    live captures)."""
    variety = _variety(svc, session_id, None)
    _, poses = _ready_poses(svc, session_id)
    ids = [p.id for p in poses]
    if not variety["ready_for_guidance"]:
        raise Problem(409, "not-enough-poses", f"session {session_id}: guidance needs >= 3 "
                      f"varied ready poses ({len(ids)} ready): {variety['reason']}")
    key = hashlib.sha1(json.dumps([PLAN_VERSION, model, min_visible, *ids]).encode()
                       ).hexdigest()[:16]
    final = svc.store.dir_for(session_id) / "guidance" / key
    with _plan_lock(final):
        if (final / "next-pose.json").is_file():
            return final, key
        tmp = svc.store.temp_dir()
        header = {"session_id": session_id, "model": model, "poses_used": ids,
                  "min_screen_visible": min_visible}
        try:
            svc.executor.submit(guidance_task, str(svc.store.dir_for(session_id) / "plan.json"),
                                [str(svc.store.file(p, "maps.npz")) for p in ids], model,
                                str(tmp), header, min_visible).result()
        except ValueError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            raise Problem(422, "guidance-failed", f"session {session_id}: {exc}") from None
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        final.parent.mkdir(parents=True, exist_ok=True)
        svc.store.replace_dir(tmp, final)
    return final, key


@router.get("/sessions/{session_id}/next-pose")
def next_pose(session_id: str, svc: Svc, model: Model = "opencv-rational",
              min_screen_visible: Visible = DEFAULT_MIN_VISIBLE) -> JSONResponse:
    """The screen pose that most reduces the worst predicted ray uncertainty over the sensor,
    planned from the session's own varied ready poses (>= 3; 409 with the reason otherwise):
    `screen_pose` (rvec rad, tvec_mm) for `POST /sessions/{id}/poses` on a simulated or
    robotic rig, `placement` in words, `outline_px` (the screen's corners in camera pixels),
    the predicted worst 1-sigma now and after, `helps` and `advice` (whether any pose still
    helps), and `image`, the URL of its picture (it changes whenever the plan does).
    `min_screen_visible` (by default below 1) lets the suggested screen reach past the image's
    edge; `screen_visible_fraction` says how much of it the camera sees. On a session of
    several cameras `cameras` says what the pose does for each: `serves`, the worst sigma now
    and after, `outline_px` in that camera's pixels (null where it does not see the screen)
    and `image`, the URL of that camera's picture."""
    rig = rig_next_pose(svc, session_id, model, min_screen_visible)
    if rig is not None:  # several cameras: `cameras` says what the pose does for each
        return JSONResponse(rig, headers={"Cache-Control": "no-cache", "ETag": f'"{rig["key"]}"'})
    folder, key = _guidance_dir(svc, session_id, model, min_screen_visible)
    out = json.loads((folder / "next-pose.json").read_text())
    out["image"] = f"/sessions/{session_id}/next-pose.png?model={model}&key={key}"
    out["key"] = key
    return JSONResponse(out, headers={"Cache-Control": "no-cache", "ETag": f'"{key}"'})


@router.get("/sessions/{session_id}/next-pose.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}})
def next_pose_image(session_id: str, svc: Svc, model: Model = "opencv-rational",
                    min_screen_visible: Visible = DEFAULT_MIN_VISIBLE,
                    key: Annotated[str | None, Query(
                        pattern="^[0-9a-f]{16}$",
                        description="the plan's key from GET next-pose: that plan's picture, "
                                    "cacheable for good; without it, the current plan's")] = None,
                    camera: CameraQuery = None) -> Response:
    """Predicted ray-uncertainty maps now and after the suggested pose, with its outline; on a
    session of several cameras, `camera`'s ray uncertainty now with the suggested screen
    where that camera sees it (404 naming the cameras when it is missing or unknown)."""
    if key is not None:
        with svc.db.session() as s:
            get_session(s, session_id)
        if (rig_plan_dir(svc, session_id, key) / "next-pose.json").is_file():
            return Response(rig_picture(svc, session_id, key, camera).read_bytes(),
                            media_type="image/png",
                            headers={"Cache-Control": _IMMUTABLE, "ETag": f'"{key}"'})
        path = svc.store.dir_for(session_id) / "guidance" / key / "next-pose.png"
        if not path.is_file():
            raise Problem(404, "not-found", f"session {session_id} has no next-pose plan with "
                          f"key {key}; GET /sessions/{session_id}/next-pose for the current one")
        if camera is not None:
            raise Problem(404, "not-found", f"camera: session {session_id}'s next-pose plan "
                          f"{key} is of one camera: leave camera out")
        return Response(path.read_bytes(), media_type="image/png",
                        headers={"Cache-Control": _IMMUTABLE, "ETag": f'"{key}"'})
    rig = rig_next_pose(svc, session_id, model, min_screen_visible)
    if rig is not None:
        return Response(rig_picture(svc, session_id, rig["key"], camera).read_bytes(),
                        media_type="image/png",
                        headers={"Cache-Control": "no-cache", "ETag": f'"{rig["key"]}"'})
    if camera is not None:
        raise Problem(404, "not-found", f"camera: session {session_id} was captured on one "
                      "camera: leave camera out")
    folder, current = _guidance_dir(svc, session_id, model, min_screen_visible)
    return Response((folder / "next-pose.png").read_bytes(), media_type="image/png",
                    headers={"Cache-Control": "no-cache", "ETag": f'"{current}"'})


@router.get("/sessions/{session_id}/starting-poses")
def starting_poses_route(session_id: str, svc: Svc,
                         count: Annotated[int, Query(ge=1, le=12, description="poses to plan")
                                          ] = 5,
                         hfov_deg: Hfov = None, lens: Lens = "pinhole") -> JSONResponse:
    """A varied starting set planned from the rig's camera and screen alone (works with no
    pose yet): each item has `screen_pose` (rvec rad, tvec_mm, as `PUT /rigs/{id}/screen-pose`
    takes it), `placement` in words, `outline_px` (the screen's 4 corners in camera pixels,
    corner (0, 0) first) and `captured_by` (a ready pose that already matches it, or null);
    `camera` says which nominal lens the prediction assumed (`lens`, `hfov_deg`)."""
    sess, poses = _ready_poses(svc, session_id)
    camera = _camera(svc, sess, poses, hfov_deg, lens)
    screen = plan_from_dict(sess.plan).screen
    size = camera.model.image_size
    try:
        planned = starting_poses(camera, screen, count)
    except ValueError as exc:
        raise Problem(422, "guidance-failed", f"session {session_id}: {exc}") from None
    observed = _observed(svc, sess, poses, camera)
    items = [{**p.to_json(size), "captured_by": captured_by(p, observed, size)}
             for p in planned]
    return JSONResponse({"session_id": session_id, "camera": camera.to_json(), "poses": items},
                        headers={"Cache-Control": "no-cache"})


@router.get("/sessions/{session_id}/pose-variety")
def pose_variety_route(session_id: str, svc: Svc, hfov_deg: Hfov = None,
                       lens: Lens = "pinhole") -> JSONResponse:
    """Whether the ready poses are varied enough (no fit): `ready_for_guidance`,
    `ready_for_calibration` per model, `reason` in words and `duplicates` (each pose that
    repeats an earlier one: `pose_id`, `repeats`, `similarity` 0..1)."""
    return JSONResponse(_variety(svc, session_id, hfov_deg, lens),
                        headers={"Cache-Control": "no-cache"})


@router.get("/sessions/{session_id}/coverage.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}})
def coverage_image(session_id: str, svc: Svc) -> Response:
    """How many of the session's decoded poses saw each camera pixel (a colour bar counts)."""
    with svc.db.session() as s:
        get_session(s, session_id)
        ids = list(s.scalars(select(PoseRecord.id).where(
            PoseRecord.session_id == session_id,
            PoseRecord.status.in_(("ready", "flagged")))))
    if not ids:
        raise Problem(409, "not-enough-poses", f"session {session_id} has no decoded poses yet")
    counts = np.sum([load_maps(pose_maps_path(svc, p)).mask for p in ids], axis=0)
    return Response(count_png(counts, f"sensor coverage by {len(ids)} poses"),
                    media_type="image/png", headers={"Cache-Control": "no-cache"})
