"""Batch re-calibration: N sessions x M model settings as one job spread over the executor.

`POST /batches/calibrations` creates one calibration resource per (session, model setting),
all tied to one job (`api.jobs.calibrations.BatchCalibrateJob`); the job runs them as
sub-tasks (`api.worker.dask_batch`), so
on a Dask cluster they spread over the workers. Each calibration ends `succeeded` or
`failed` with its own reason; cancelling the job cancels every one still running.
"""

from __future__ import annotations

import time
from typing import Annotated, Any

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, RootModel
from sqlalchemy import select

from api.db import CalibrationRecord, PoseRecord
from api.jobs.calibrations import BatchCalibrateJob, BatchEntry
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, accepted, get_session
from api.schemas import IdStr, per_model, strict_config
from api.services import Services, get_services
from api.store import new_id
from calibration import model_spec

router = APIRouter(tags=["calibrations"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]

MAX_BATCH_ITEMS = 500


class _SettingFields(BaseModel):
    """A model setting has nothing besides its model and typed options."""

    model_config = ConfigDict(extra="forbid")


class ModelSetting(RootModel[per_model(_SettingFields, "ModelSetting")]):  # type: ignore[misc]
    """One model with its fit options (typed per model, from the model registry)."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"model": "sgcc", "options": {"cells": [24, 16]}}]})


class BatchCalibrationCreate(BaseModel):
    """Calibrate every ready pose of each session with each model setting."""

    model_config = strict_config(
        {"session_ids": ["ses_0123456789abcdef", "ses_fedcba9876543210"],
         "models": [{"model": "opencv-rational"}, {"model": "sgcc"}]}
    )
    session_ids: list[IdStr] = Field(min_length=1, max_length=MAX_BATCH_ITEMS)
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


def _options(setting: Any) -> dict[str, Any]:
    """The options the client set (JSON-able), as stored and handed to the fit."""
    return setting.options.model_dump(mode="json", exclude_unset=True)


def _check_pose_counts(poses: dict[str, list[str]], models: list[str]) -> None:
    """422 unless every session has the ready poses every model needs."""
    for model in dict.fromkeys(models):
        need = model_spec(model).min_poses
        for sid, ids in poses.items():
            if len(ids) < need:
                raise Problem(422, "validation-error",
                              f"session_ids: session {sid} has {len(ids)} ready poses; "
                              f"{model} needs >= {need}")


@router.post("/batches/calibrations", status_code=202, response_model=None,
             responses={202: {"description": "batch job accepted; Location: /jobs/<id>"}})
def create_batch(body: BatchCalibrationCreate, svc: Svc) -> JSONResponse:
    """One job calibrating sessions x model settings; one calibration resource per item."""
    session_ids = list(dict.fromkeys(body.session_ids))
    n_items = len(session_ids) * len(body.models)
    if n_items > MAX_BATCH_ITEMS:
        raise Problem(422, "validation-error",
                      f"session_ids x models: {n_items} items, at most {MAX_BATCH_ITEMS}")
    with svc.db.claim_session() as s:
        poses = {sid: _ready_poses(s, sid) for sid in session_ids}
        _check_pose_counts(poses, [m.root.model for m in body.models])
        entries = [BatchEntry(new_id("cal"), sid, tuple(poses[sid]), setting.model,
                              _options(setting))
                   for sid in session_ids for setting in (m.root for m in body.models)]
        job = BatchCalibrateJob(svc=svc, entries=entries)
        state = svc.jobs.create(s, job)
        s.add_all(CalibrationRecord(id=e.cal_id, session_id=e.session_id, model=e.model,
                                    pose_ids=list(e.pose_ids), heldout_pose_ids=[],
                                    options=e.options, status="queued", job_id=state.id,
                                    exports=[], created_at=time.time())
                  for e in entries)
    return accepted(svc.jobs.start(state.id, job))
