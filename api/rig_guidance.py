"""The next pose of a session captured on several cameras: every camera's decoded maps of
the ready poses, planned on a worker (api/worker/rig_tasks.py) and cached per set of poses,
so a repeated request is a file read; the plan's folder also holds a picture per camera."""

from __future__ import annotations

import hashlib
import json
import shutil
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import select

from api.db import PoseRecord
from api.pose_path import camera_maps_path, pose_camera_names
from api.problems import Problem
from api.worker.rig_tasks import RIG_PICTURE, rig_guidance_task

if TYPE_CHECKING:
    from api.services import Services

RIG_PLAN_VERSION = 2  # part of the cache key: a changed planner never serves an older plan
_lock = threading.Lock()  # one rig plan at a time: each is seconds of CPU on a worker


def rig_maps(svc: Services, session_id: str) -> tuple[list[str], dict[str, dict[str, str]]]:
    """The session's ready poses and, if they were captured on several cameras, camera ->
    pose -> maps path (reference camera first); ({...}, {}) for a one-camera session."""
    with svc.db.session() as s:
        ids = list(s.scalars(select(PoseRecord.id).where(
            PoseRecord.session_id == session_id, PoseRecord.status == "ready")
            .order_by(PoseRecord.index)))
    maps: dict[str, dict[str, str]] = {}
    for pid in ids:
        pose_dir = svc.store.dir_for(pid)
        for cam in pose_camera_names(pose_dir):
            path = camera_maps_path(pose_dir, cam)
            if path.is_file():
                maps.setdefault(cam, {})[pid] = str(path)
    return ids, maps


def rig_plan_dir(svc: Services, session_id: str, key: str) -> Path:
    """The folder of the rig plan with that key (next-pose.json and the pictures)."""
    return svc.store.dir_for(session_id) / "guidance" / f"rig-{key}"


def rig_picture(svc: Services, session_id: str, key: str, camera: str | None) -> Path:
    """One camera's picture of the rig plan `key`; 404 naming the plan's cameras when
    `camera` is missing or not one of them."""
    folder = rig_plan_dir(svc, session_id, key)
    names = [c["camera"] for c in json.loads((folder / "next-pose.json").read_text())["cameras"]]
    if camera not in names:
        said = "no camera given" if camera is None else f"no camera {camera!r}"
        raise Problem(404, "not-found", f"camera: session {session_id}'s next-pose plan {key} "
                      f"has {said}; it has a picture per camera: ?camera= one of "
                      f"{', '.join(names)}")
    return folder / RIG_PICTURE.format(camera=camera)


def rig_next_pose(svc: Services, session_id: str, model: str, min_visible: float
                  ) -> dict[str, Any] | None:
    """The rig's next-pose plan (None for a session of one camera), each camera with the URL
    of its picture (keyed: it changes whenever the plan does)."""
    ids, maps = rig_maps(svc, session_id)
    if not maps:
        return None
    key = hashlib.sha1(json.dumps([RIG_PLAN_VERSION, model, min_visible, *ids]).encode()
                       ).hexdigest()[:16]
    final = rig_plan_dir(svc, session_id, key)
    with _lock:
        if not (final / "next-pose.json").is_file():
            _plan(svc, session_id, maps, model, min_visible, final,
                  {"session_id": session_id, "model": model, "poses_used": ids,
                   "min_screen_visible": min_visible, "reference": next(iter(maps))})
    out = json.loads((final / "next-pose.json").read_text())
    out["key"] = key
    for cam in out["cameras"]:
        cam["image"] = (f"/sessions/{session_id}/next-pose.png?camera={cam['camera']}"
                        f"&key={key}")
    return out


def _plan(svc: Services, session_id: str, maps: dict[str, dict[str, str]], model: str,
          min_visible: float, final: Path, header: dict[str, Any]) -> None:
    tmp = svc.store.temp_dir()
    try:
        svc.executor.submit(rig_guidance_task, str(svc.store.dir_for(session_id) / "plan.json"),
                            maps, header["reference"], model, str(tmp), header,
                            min_visible).result()
    except ValueError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise Problem(409 if "needs >=" in str(exc) or "share no" in str(exc) else 422,
                      "not-enough-poses" if "needs >=" in str(exc) else "guidance-failed",
                      f"session {session_id}: {exc}") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    final.parent.mkdir(parents=True, exist_ok=True)
    svc.store.replace_dir(tmp, final)


def pose_maps_path(svc: Services, pose_id: str) -> Path:
    """A pose's maps for the single-camera views (variety, starting poses, coverage): the
    reference camera's on a pose of several cameras."""
    pose_dir = svc.store.dir_for(pose_id)
    names = pose_camera_names(pose_dir)
    return camera_maps_path(pose_dir, names[0]) if names else svc.store.file(pose_id, "maps.npz")
