"""Pose guidance: the predicted ray uncertainty of a session and the next pose to capture."""

from __future__ import annotations

import hashlib
import json
import shutil
import threading
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Query
from fastapi.responses import Response
from sqlalchemy import select

from api.db import PoseRecord
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, get_session
from api.services import Services, get_services
from api.worker.guidance_task import guidance_task
from calibration import count_png
from calibration.shared.maps import load_maps

router = APIRouter(tags=["guidance"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
Model = Annotated[str, Query(description="parametric model the prediction uses",
                             pattern="^(opencv5|opencv-rational|fisheye)$")]
_locks: dict[str, threading.Lock] = {}  # one per cached plan: a plan is computed once, while
_locks_guard = threading.Lock()  # other sessions' (and models') plans go on at the same time


def _plan_lock(final: Path) -> threading.Lock:
    """The lock of one cached plan's folder."""
    with _locks_guard:
        return _locks.setdefault(str(final), threading.Lock())


def _guidance_dir(svc: Services, session_id: str, model: str) -> tuple[Path, list[str]]:
    """Cached guidance for the session's current ready poses, computed on first request by
    the executor's worker (the fit takes seconds of CPU; the server paces live captures)."""
    with svc.db.session() as s:
        get_session(s, session_id)
        ids = list(s.scalars(select(PoseRecord.id).where(
            PoseRecord.session_id == session_id, PoseRecord.status == "ready")
            .order_by(PoseRecord.index)))
    if len(ids) < 3:
        raise Problem(409, "not-enough-poses", f"session {session_id}: guidance needs >= 3 ready "
                      f"poses to fit a model (has {len(ids)}); capture varied, tilted poses first")
    key = hashlib.sha1(json.dumps([model, *ids]).encode()).hexdigest()[:16]
    final = svc.store.dir_for(session_id) / "guidance" / key
    with _plan_lock(final):
        if (final / "next-pose.json").is_file():
            return final, ids
        tmp = svc.store.temp_dir()
        header = {"session_id": session_id, "model": model, "poses_used": ids}
        try:
            svc.executor.submit(guidance_task, str(svc.store.dir_for(session_id) / "plan.json"),
                                [str(svc.store.file(p, "maps.npz")) for p in ids], model,
                                str(tmp), header).result()
        except ValueError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            raise Problem(422, "guidance-failed", f"session {session_id}: {exc}") from None
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        final.parent.mkdir(parents=True, exist_ok=True)
        svc.store.replace_dir(tmp, final)
    return final, ids


@router.get("/sessions/{session_id}/next-pose")
def next_pose(session_id: str, svc: Svc, model: Model = "opencv-rational") -> dict[str, Any]:
    """The screen pose that most reduces the worst predicted ray uncertainty over the sensor,
    planned from the session's own ready poses (>= 3): `screen_pose` (rvec rad, tvec_mm) for
    `POST /sessions/{id}/poses` on a simulated or robotic rig, the placement in words
    (distance, tilt, where its centre appears), and the predicted worst 1-sigma now and after."""
    folder, _ = _guidance_dir(svc, session_id, model)
    out = json.loads((folder / "next-pose.json").read_text())
    out["image"] = f"/sessions/{session_id}/next-pose.png?model={model}"
    return out


@router.get("/sessions/{session_id}/next-pose.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}})
def next_pose_image(session_id: str, svc: Svc, model: Model = "opencv-rational") -> Response:
    """Predicted ray-uncertainty maps now and after the suggested pose, with its outline."""
    folder, _ = _guidance_dir(svc, session_id, model)
    return Response((folder / "next-pose.png").read_bytes(), media_type="image/png")


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
    counts = np.sum([load_maps(svc.store.file(p, "maps.npz")).mask for p in ids], axis=0)
    return Response(count_png(counts, f"sensor coverage by {len(ids)} poses"),
                    media_type="image/png")
