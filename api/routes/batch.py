"""Batch re-calibration: N sessions x M model settings as one job spread over the executor.

`POST /batches/calibrations` creates one calibration resource per (session, model setting),
all tied to one job; the job runs them as sub-tasks (`calibration.worker.dask_batch`), so
on a Dask cluster they spread over the workers. Each calibration ends `succeeded` or
`failed` with its own reason; cancelling the job cancels every one still running.
"""

from __future__ import annotations

import time
from typing import Annotated, Any

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from sqlalchemy import select

from api.db import CalibrationRecord, PoseRecord
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, accepted, get_session
from api.schemas import ModelName, _strict
from api.services import Services, get_services
from api.store import new_id
from calibration.progress import TaskContext
from calibration.worker.dask_batch import BatchItem, run_batch

router = APIRouter(tags=["calibrations"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]

MAX_BATCH_ITEMS = 500


class ModelSetting(BaseModel):
    """One model with its fit options."""

    model_config = _strict({"model": "sgcc", "options": {}})
    model: ModelName
    options: dict[str, Any] = Field(default_factory=dict)


class BatchCalibrationCreate(BaseModel):
    """Calibrate every ready pose of each session with each model setting."""

    model_config = _strict(
        {"session_ids": ["ses_0123456789abcdef", "ses_fedcba9876543210"],
         "models": [{"model": "opencv-rational"}, {"model": "sgcc"}]}
    )
    session_ids: list[str] = Field(min_length=1, max_length=MAX_BATCH_ITEMS)
    models: list[ModelSetting] = Field(min_length=1, max_length=50)


def _ready_poses(s: Any, session_id: str) -> list[str]:
    """Ids of the session's ready poses, in capture order; 409 if there are none."""
    get_session(s, session_id)
    ids = list(s.scalars(
        select(PoseRecord.id).where(PoseRecord.session_id == session_id,
                                    PoseRecord.status == "ready").order_by(PoseRecord.index)))
    if not ids:
        raise Problem(409, "no-poses", f"session {session_id} has no ready poses to calibrate")
    return ids


@router.post("/batches/calibrations", status_code=202, response_model=None,
             responses={202: {"description": "batch job accepted; Location: /jobs/<id>"}})
def create_batch(body: BatchCalibrationCreate, svc: Svc) -> JSONResponse:
    """One job calibrating sessions x model settings; one calibration resource per item."""
    session_ids = list(dict.fromkeys(body.session_ids))
    n_items = len(session_ids) * len(body.models)
    if n_items > MAX_BATCH_ITEMS:
        raise Problem(422, "validation-error",
                      f"session_ids x models: {n_items} items, at most {MAX_BATCH_ITEMS}")
    plan: list[tuple[str, str, list[str], ModelSetting]] = []
    cal_ids = [new_id("cal") for _ in range(n_items)]
    with svc.db.claim_session() as s:
        poses = {sid: _ready_poses(s, sid) for sid in session_ids}
        job = svc.jobs.create(s, "calibrate", "/calibrations", None, total=n_items,
                              claims=tuple(cal_ids))
        for sid in session_ids:
            for setting in body.models:
                cid = cal_ids[len(plan)]
                s.add(CalibrationRecord(id=cid, session_id=sid, model=setting.model,
                                        pose_ids=poses[sid], heldout_pose_ids=[],
                                        options=setting.options, status="queued",
                                        job_id=job.id, exports=[], created_at=time.time()))
                plan.append((cid, sid, poses[sid], setting))
    cids = [cid for cid, *_ in plan]

    def run(ctx: TaskContext) -> dict[str, Any]:
        with svc.db.session() as s:
            for cid in cids:
                s.get(CalibrationRecord, cid).status = "running"
        # workers write into the job's staging folder; finished items are moved into place
        with svc.store.staging(ctx.job_id) as staged:
            items = [
                BatchItem(name=cid, plan_path=str(svc.store.dir_for(sid) / "plan.json"),
                          maps_paths=tuple(str(svc.store.file(p, "maps.npz")) for p in pose_ids),
                          model=setting.model, out_dir=str(staged / cid),
                          options=dict(setting.options))
                for cid, sid, pose_ids, setting in plan
            ]
            result = run_batch(svc.executor, items, ctx)
            for outcome in result.get("items", []):
                if outcome["status"] == "succeeded":
                    cid = outcome["name"]
                    names = ["model.json", "result.json", *outcome["result"].get("exports", [])]
                    svc.store.commit(staged / cid, names, svc.store.dir_for(cid))
                outcome.pop("out_dir", None)
        return result

    def ok(s: Any, result: dict[str, Any]) -> None:
        for outcome in result.get("items", []):
            c = s.get(CalibrationRecord, outcome["name"])
            c.status = outcome["status"]
            if outcome["status"] == "succeeded":
                c.stats = outcome["result"].get("stats")
                c.exports = ["model.json", "result.json", *outcome["result"].get("exports", [])]
            else:
                c.error = outcome.get("error")

    def fail(s: Any, status: str, error: str) -> None:
        for cid in cids:
            c = s.get(CalibrationRecord, cid)
            if c.status in ("queued", "running"):
                c.status, c.error = status, error

    svc.jobs.start(job.id, run, ok, fail)
    return accepted(svc.jobs.get(job.id) or {})
