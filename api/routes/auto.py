"""The closed loop over REST: `POST /sessions/{id}/auto` starts a job that moves the
session rig's robot, captures, refits and stops at the target or the pose budget;
`GET /sessions/{id}/auto` reads the latest run's log (also while it runs)."""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field

from acquisition.mover import Workspace
from api.jobs.auto import LOG, AutoJob, rig_mover
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, accepted, get_session
from api.schemas import strict_config
from api.services import Services, get_services
from calibration.shared.plan import plan_from_dict

router = APIRouter(tags=["auto"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
MAX_BUDGET = 100


class AutoTarget(BaseModel):
    """When the loop may stop: every given figure at or below its value."""

    model_config = strict_config({"worst_ray_sigma_urad": 50, "handeye_sigma_mm": 0.2})
    worst_ray_sigma_urad: float = Field(gt=0, allow_inf_nan=False, description=(
        "the worst predicted 1-sigma ray direction uncertainty over the sensor (urad)"))
    handeye_sigma_mm: float | None = Field(default=None, gt=0, allow_inf_nan=False)
    handeye_sigma_mrad: float | None = Field(default=None, gt=0, allow_inf_nan=False)


class AutoCreate(BaseModel):
    """A closed-loop run on the session's rig, whose config has a `mover` (docs/robots.md)."""

    model_config = strict_config({
        "target": {"worst_ray_sigma_urad": 50, "handeye_sigma_mm": 0.2},
        "budget": 12, "model": "opencv5", "mount": "eye-in-hand",
        "workspace": {"min_mm": [-800, -800, 0], "max_mm": [800, 800, 1200]}})
    target: AutoTarget
    budget: int = Field(ge=4, le=MAX_BUDGET, description="the most poses to take")
    model: Literal["opencv5", "opencv-rational", "fisheye"] = Field(
        default="opencv5", description="parametric model the planning and hand-eye fit use")
    mount: Literal["eye-in-hand", "eye-to-hand"]
    workspace: dict[str, Any] | None = Field(default=None, description=(
        "where the flange may go: {min_mm [3], max_mm [3], optional home_R, max_angle_deg}; "
        "the mover's own workspace applies as well"))
    noise_dn: float | None = Field(default=None, gt=0, allow_inf_nan=False)


@router.post("/sessions/{session_id}/auto", status_code=202, response_model=None,
             responses={202: {"description": "auto job accepted; Location: /jobs/<id>"}})
def start_auto(session_id: str, body: AutoCreate, svc: Svc) -> JSONResponse:
    """Plan, move, capture and refit until `target` is met or `budget` poses are taken."""
    workspace = None
    if body.workspace is not None:
        try:
            workspace = Workspace.from_json(body.workspace, "workspace")
        except ValueError as exc:
            raise Problem(422, "validation-error", str(exc)) from None
    with svc.db.session() as s:
        sess = get_session(s, session_id)
        rig_id, plan_data = sess.rig_id, sess.plan
    if rig_id is None:
        raise Problem(409, "no-rig", f"session {session_id} has no rig: the loop needs a rig "
                      "with a mover")
    if rig_mover(svc.rigs.handle(rig_id).rig) is None:
        raise Problem(409, "no-mover", f"rig {rig_id} has no mover: add a `mover` section "
                      "(backend = \"http\" for a robot server, see docs/robots.md) to its "
                      "config, then start the loop again")
    job = AutoJob(svc=svc, session_id=session_id, rig_id=rig_id,
                  plan=plan_from_dict(plan_data, f"session {session_id} plan"),
                  mount=body.mount, model=body.model, budget=body.budget,
                  target_urad=body.target.worst_ray_sigma_urad,
                  target_handeye_mm=body.target.handeye_sigma_mm,
                  target_handeye_mrad=body.target.handeye_sigma_mrad,
                  workspace=workspace, noise_dn=body.noise_dn)
    with svc.db.claim_session() as s:
        state = svc.jobs.create(s, job)
    return accepted(svc.jobs.start(state.id, job))


@router.get("/sessions/{session_id}/auto")
def read_auto(session_id: str, svc: Svc) -> dict[str, Any]:
    """The latest auto run's log: poses taken (flange pose, reason, predicted and fitted
    worst sigma), skipped candidates and why, the hand-eye with its sigma, the stop reason
    (null while it runs)."""
    with svc.db.session() as s:
        get_session(s, session_id)
    path = svc.store.dir_for(session_id) / LOG
    if not path.is_file():
        raise Problem(404, "not-found", f"session {session_id} has no auto run yet; POST "
                      f"/sessions/{session_id}/auto to start one")
    return json.loads(path.read_text())
