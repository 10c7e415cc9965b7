"""Hand-eye of a session: its poses' maps with the robot pose of each (phasecal.robot-poses/1
keyed by pose id), as a job; the latest result (phasecal.handeye/1) is kept per session."""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from api.db import PoseRecord
from api.jobs.handeye import RESULT, HandEyeJob
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, accepted, get_session
from api.schemas import ModelName, strict_config
from api.services import Services, get_services
from calibration import MIN_HANDEYE_VIEWS, RobotPosesError, robot_poses_from_dict

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
        "phasecal.robot-poses/1 whose VIEW keys are pose ids of the session"))
    options: dict[str, Any] = Field(default_factory=dict, max_length=50)


@router.post("/sessions/{session_id}/handeye", status_code=202, response_model=None,
             responses={202: {"description": "hand-eye job accepted; Location: /jobs/<id>"}})
def start_handeye(session_id: str, body: HandEyeCreate, svc: Svc) -> JSONResponse:
    """Fit the camera to the poses named in `robot_poses`, then the hand-eye."""
    try:
        robot = robot_poses_from_dict(body.robot_poses, "robot_poses")
    except RobotPosesError as exc:
        raise Problem(422, "validation-error", str(exc)) from None
    if len(robot.poses) > MAX_VIEWS:
        raise Problem(422, "validation-error", f"robot_poses.poses: at most {MAX_VIEWS} views")
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
        if len(robot.poses) < MIN_HANDEYE_VIEWS:
            raise Problem(409, "too-few-poses", f"hand-eye needs >= {MIN_HANDEYE_VIEWS} poses "
                          f"with robot poses, got {len(robot.poses)}")
        job = HandEyeJob(svc=svc, session_id=session_id, mount=body.mount, model=body.model,
                         robot_poses=body.robot_poses, pose_ids=list(robot.poses),
                         options=body.options)
        state = svc.jobs.create(s, job)
    return accepted(svc.jobs.start(state.id, job))


@router.get("/sessions/{session_id}/handeye")
def read_handeye(session_id: str, svc: Svc) -> dict[str, Any]:
    """The session's latest hand-eye result (phasecal.handeye/1)."""
    with svc.db.session() as s:
        get_session(s, session_id)
    path = svc.store.dir_for(session_id) / RESULT
    if not path.is_file():
        raise Problem(404, "not-found", f"session {session_id} has no hand-eye yet; POST "
                      f"/sessions/{session_id}/handeye to compute it")
    return json.loads(path.read_text())
