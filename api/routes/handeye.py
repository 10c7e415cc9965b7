"""Hand-eye of a session (its poses' maps) or of a target session (its views' observations)
with the robot pose of each (phasecal.robot-poses/1 keyed by pose or view id), as a job; the
latest result (phasecal.handeye/1) is kept per session."""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from api.db import PoseRecord, TargetSessionRecord, TargetViewRecord
from api.jobs.handeye import RESULT, HandEyeJob
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, accepted, get_session
from api.schemas import ModelName, strict_config
from api.services import Services, get_services
from calibration import (
    MIN_HANDEYE_VIEWS,
    RobotPoses,
    RobotPosesError,
    robot_poses_from_dict,
)

router = APIRouter(tags=["hand-eye"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
MAX_VIEWS = 500


class HandEyeCreate(BaseModel):
    """Hand-eye from a session's ready poses and the robot's pose for each (docs/robots.md)."""

    model_config = strict_config({
        "mount": "eye-in-hand", "model": "opencv5",
        "robot_poses": {"format": "phasecal.robot-poses/1",
                        "repeatability": {"mm": 0.02, "deg": 0.005},
                        "poses": {"pose_0123456789abcdef": {
                            "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t_mm": [400, 0, 300]}}}})
    mount: Literal["eye-in-hand", "eye-to-hand"]
    model: ModelName
    robot_poses: dict[str, Any] = Field(description=(
        "phasecal.robot-poses/1 whose VIEW keys are pose ids of the session (view ids of a "
        "target session)"))
    options: dict[str, Any] = Field(default_factory=dict, max_length=50)


@router.post("/sessions/{session_id}/handeye", status_code=202, response_model=None,
             responses={202: {"description": "hand-eye job accepted; Location: /jobs/<id>"}})
def start_handeye(session_id: str, body: HandEyeCreate, svc: Svc) -> JSONResponse:
    """Fit the camera to the poses named in `robot_poses`, then the hand-eye."""
    robot = _robot_poses(body)
    with svc.db.session() as s:
        get_session(s, session_id)
        for pid in robot.poses:
            pose = s.get(PoseRecord, pid)
            if pose is None or pose.session_id != session_id:
                raise Problem(422, "validation-error", f"robot_poses.poses: {pid!r} is not a "
                              f"pose of session {session_id}")
            if pose.status not in ("ready", "flagged"):
                raise Problem(409, "not-ready", f"robot_poses.poses: pose {pid} is "
                              f"{pose.status}; its maps exist once it is ready")
        _check_count(len(robot.poses))
        job = HandEyeJob(svc=svc, session_id=session_id, mount=body.mount, model=body.model,
                         robot_poses=body.robot_poses, source="maps",
                         paths={p: str(svc.store.file(p, "maps.npz")) for p in robot.poses},
                         options=body.options,
                         resource_path=f"/sessions/{session_id}/handeye")
        state = svc.jobs.create(s, job)
    return accepted(svc.jobs.start(state.id, job))


@router.post("/target-sessions/{session_id}/handeye", status_code=202, response_model=None,
             responses={202: {"description": "hand-eye job accepted; Location: /jobs/<id>"}})
def start_target_handeye(session_id: str, body: HandEyeCreate, svc: Svc) -> JSONResponse:
    """Fit the camera to the target session's views named in `robot_poses` (uploaded as
    observation files or detected images), then the hand-eye."""
    robot = _robot_poses(body)
    with svc.db.session() as s:
        if s.get(TargetSessionRecord, session_id) is None:
            raise Problem(404, "not-found", f"target session {session_id!r} does not exist")
        for vid in robot.poses:
            view = s.get(TargetViewRecord, vid)
            if view is None or view.session_id != session_id:
                raise Problem(422, "validation-error", f"robot_poses.poses: {vid!r} is not a "
                              f"view of target session {session_id}")
        _check_count(len(robot.poses))
        job = HandEyeJob(svc=svc, session_id=session_id, mount=body.mount, model=body.model,
                         robot_poses=body.robot_poses, source="observations",
                         paths={v: str(svc.store.file(session_id, f"{v}.npz"))
                                for v in robot.poses},
                         options=body.options,
                         resource_path=f"/target-sessions/{session_id}/handeye")
        state = svc.jobs.create(s, job)
    return accepted(svc.jobs.start(state.id, job))


def _robot_poses(body: HandEyeCreate) -> RobotPoses:
    """The request's robot poses, or a 422 naming what is wrong."""
    try:
        robot = robot_poses_from_dict(body.robot_poses, "robot_poses")
    except RobotPosesError as exc:
        raise Problem(422, "validation-error", str(exc)) from None
    if len(robot.poses) > MAX_VIEWS:
        raise Problem(422, "validation-error", f"robot_poses.poses: at most {MAX_VIEWS} views")
    return robot


def _check_count(count: int) -> None:
    if count < MIN_HANDEYE_VIEWS:
        raise Problem(409, "too-few-poses", f"hand-eye needs >= {MIN_HANDEYE_VIEWS} views "
                      f"with robot poses, got {count}")


@router.get("/sessions/{session_id}/handeye")
def read_handeye(session_id: str, svc: Svc) -> dict[str, Any]:
    """The session's latest hand-eye result (phasecal.handeye/1)."""
    with svc.db.session() as s:
        get_session(s, session_id)
    return _result(svc, session_id, f"/sessions/{session_id}/handeye")


@router.get("/target-sessions/{session_id}/handeye")
def read_target_handeye(session_id: str, svc: Svc) -> dict[str, Any]:
    """The target session's latest hand-eye result (phasecal.handeye/1)."""
    with svc.db.session() as s:
        if s.get(TargetSessionRecord, session_id) is None:
            raise Problem(404, "not-found", f"target session {session_id!r} does not exist")
    return _result(svc, session_id, f"/target-sessions/{session_id}/handeye")


def _result(svc: Services, session_id: str, route: str) -> dict[str, Any]:
    path = svc.store.dir_for(session_id) / RESULT
    if not path.is_file():
        raise Problem(404, "not-found", f"session {session_id} has no hand-eye yet; POST "
                      f"{route} to compute it")
    return json.loads(path.read_text())
