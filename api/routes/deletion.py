"""DELETE for poses, calibrations and sessions, of screen and of target sessions: records and
files; 409 while a job uses them.

Deletes run in `Database.claim_session`, serialized with every job start, so a job cannot
claim a resource between the check and the delete. They work on a full disk: a record
delete that SQLite refuses for lack of space runs again with the database reserve released
(api/storage.py), and the reserve is taken back once the files are gone.
"""

from __future__ import annotations

import shutil
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Response
from sqlalchemy import delete, select

from api.db import (
    CalibrationRecord,
    JobLockRecord,
    PoseRecord,
    SessionRecord,
    TargetCalibrationRecord,
    TargetRigCalibrationRecord,
    TargetSessionRecord,
    TargetViewRecord,
)
from api.jobs.model import ACTIVE_JOB_STATES
from api.jobs.target_rig import used_view_ids
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, get_pose, get_session
from api.services import Services, get_services
from api.store import check_id

router = APIRouter(tags=["deletion"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]


def _busy(s: Any, ids: list[str], what: str) -> None:
    """409 if an active job claimed any of `ids`."""
    if not ids:
        return
    held = s.scalars(select(JobLockRecord).where(JobLockRecord.key.in_(ids))).first()
    if held is not None:
        raise Problem(409, "job-active", f"{what}: {held.key} is in use by active job "
                      f"{held.job_id}; cancel it or wait for it to end", job_id=held.job_id)


def _used_by_active_calibration(s: Any, session_id: str, pose_ids: set[str], what: str) -> None:
    """409 if a queued/running calibration of the session reads one of `pose_ids`."""
    for c in s.scalars(select(CalibrationRecord).where(
            CalibrationRecord.session_id == session_id,
            CalibrationRecord.status.in_(ACTIVE_JOB_STATES))):
        used = pose_ids & set(c.pose_ids or []) | pose_ids & set(c.heldout_pose_ids or [])
        if used:
            raise Problem(409, "job-active", f"{what}: pose {sorted(used)[0]} is read by "
                          f"calibration {c.id} ({c.status}, job {c.job_id})", job_id=c.job_id)


def _read_by_active_target_rig(s: Any, view_ids: set[str], what: str) -> None:
    """409 if a queued/running rig calibration from target sessions reads one of `view_ids`."""
    for c in s.scalars(select(TargetRigCalibrationRecord).where(
            TargetRigCalibrationRecord.status.in_(ACTIVE_JOB_STATES))):
        used = view_ids & used_view_ids(c)
        if used:
            raise Problem(409, "job-active", f"{what}: view {sorted(used)[0]} is read by "
                          f"rig calibration {c.id} ({c.status}, job {c.job_id})",
                          job_id=c.job_id)


def _remove_folders(svc: Services, ids: list[str]) -> None:
    """Remove the resources' files (their records are gone), then retake the space reserve."""
    for ident in ids:
        shutil.rmtree(svc.store.dir_for(ident, create=False), ignore_errors=True)
    svc.space.restore()


@router.delete("/sessions/{session_id}/poses/{pose_id}", status_code=204, response_class=Response)
def delete_pose(session_id: str, pose_id: str, svc: Svc) -> Response:
    """Delete a pose (record, frames, maps); 409 while a job captures, decodes or reads it."""

    def forget() -> None:
        with svc.db.claim_session() as s:
            pose = get_pose(s, session_id, pose_id)
            _busy(s, [pose_id], f"pose {pose_id}")
            _used_by_active_calibration(s, session_id, {pose_id}, f"pose {pose_id}")
            s.delete(pose)

    svc.space.retrying(forget)
    _remove_folders(svc, [pose_id])
    return Response(status_code=204)


@router.delete("/calibrations/{cal_id}", status_code=204, response_class=Response)
def delete_calibration(cal_id: str, svc: Svc) -> Response:
    """Delete a calibration (record, model, exports); 409 while its job runs."""
    check_id(cal_id, "cal", "calibration")

    def forget() -> None:
        with svc.db.claim_session() as s:
            cal = s.get(CalibrationRecord, cal_id)
            if cal is None:
                raise Problem(404, "not-found", f"calibration {cal_id!r} does not exist")
            _busy(s, [cal_id], f"calibration {cal_id}")
            s.delete(cal)

    svc.space.retrying(forget)
    _remove_folders(svc, [cal_id])
    return Response(status_code=204)


@router.delete("/sessions/{session_id}", status_code=204, response_class=Response)
def delete_session(session_id: str, svc: Svc) -> Response:
    """Delete a session with its poses and calibrations (records and files); 409 while any
    job uses one of them."""

    def forget() -> list[str]:
        with svc.db.claim_session() as s:
            get_session(s, session_id)
            pose_ids = list(s.scalars(select(PoseRecord.id)
                                      .where(PoseRecord.session_id == session_id)))
            cal_ids = list(s.scalars(select(CalibrationRecord.id)
                                     .where(CalibrationRecord.session_id == session_id)))
            _busy(s, pose_ids + cal_ids, f"session {session_id}")
            s.execute(delete(CalibrationRecord).where(CalibrationRecord.session_id == session_id))
            s.execute(delete(PoseRecord).where(PoseRecord.session_id == session_id))
            s.execute(delete(SessionRecord).where(SessionRecord.id == session_id))
        return [*pose_ids, *cal_ids]

    _remove_folders(svc, [*svc.space.retrying(forget), session_id])
    return Response(status_code=204)


def _target_session(s: Any, session_id: str) -> TargetSessionRecord:
    """The target session's record, or 404."""
    check_id(session_id, "ses", "target session")
    rec = s.get(TargetSessionRecord, session_id)
    if rec is None:
        raise Problem(404, "not-found", f"target session {session_id!r} does not exist")
    return rec


@router.delete("/target-sessions/{session_id}/views/{view_id}", status_code=204,
               response_class=Response)
def delete_target_view(session_id: str, view_id: str, svc: Svc) -> Response:
    """Delete a view of a target session (record and observations file); 409 while a
    hand-eye job of the session or a rig calibration's job reads the views. Calibrations
    made from it stay: they hold their own model and statistics."""
    check_id(view_id, "pose", "view")

    def forget() -> None:
        with svc.db.claim_session() as s:
            _target_session(s, session_id)
            view = s.get(TargetViewRecord, view_id)
            if view is None or view.session_id != session_id:
                raise Problem(404, "not-found",
                              f"view {view_id!r} does not exist in target session {session_id}")
            _busy(s, [f"{session_id}:handeye"], f"view {view_id}")
            _read_by_active_target_rig(s, {view_id}, f"view {view_id}")
            s.delete(view)

    svc.space.retrying(forget)
    svc.store.file(session_id, f"{view_id}.npz").unlink(missing_ok=True)
    svc.space.restore()
    return Response(status_code=204)


@router.delete("/target-sessions/{session_id}/calibrations/{cal_id}", status_code=204,
               response_class=Response)
def delete_target_calibration(session_id: str, cal_id: str, svc: Svc) -> Response:
    """Delete a calibration of a target session (record, model and figures)."""
    check_id(cal_id, "cal", "calibration")

    def forget() -> None:
        with svc.db.claim_session() as s:
            _target_session(s, session_id)
            cal = s.get(TargetCalibrationRecord, cal_id)
            if cal is None or cal.session_id != session_id:
                raise Problem(404, "not-found", f"calibration {cal_id!r} does not exist in "
                              f"target session {session_id}")
            s.delete(cal)

    svc.space.retrying(forget)
    _remove_folders(svc, [cal_id])
    return Response(status_code=204)


@router.delete("/target-sessions/{session_id}", status_code=204, response_class=Response)
def delete_target_session(session_id: str, svc: Svc) -> Response:
    """Delete a target session with its views, calibrations and hand-eye result; 409 while a
    hand-eye job of the session or a rig calibration's job reading its views runs. Rig
    calibrations made from it and other sessions stay (they hold their own rig model)."""

    def forget() -> list[str]:
        with svc.db.claim_session() as s:
            _target_session(s, session_id)
            _busy(s, [f"{session_id}:handeye"], f"target session {session_id}")
            _read_by_active_target_rig(
                s, set(s.scalars(select(TargetViewRecord.id).where(
                    TargetViewRecord.session_id == session_id))),
                f"target session {session_id}")
            cal_ids = list(s.scalars(select(TargetCalibrationRecord.id).where(
                TargetCalibrationRecord.session_id == session_id)))
            s.execute(delete(TargetCalibrationRecord)
                      .where(TargetCalibrationRecord.session_id == session_id))
            s.execute(delete(TargetViewRecord).where(TargetViewRecord.session_id == session_id))
            s.execute(delete(TargetSessionRecord).where(TargetSessionRecord.id == session_id))
        return cal_ids

    _remove_folders(svc, [*svc.space.retrying(forget), session_id])
    return Response(status_code=204)


@router.delete("/target-rig-calibrations/{cal_id}", status_code=204, response_class=Response)
def delete_target_rig_calibration(cal_id: str, svc: Svc) -> Response:
    """Delete a rig calibration from target sessions (record and rig model); 409 while its
    job runs. The sessions and views it read stay."""
    check_id(cal_id, "cal", "calibration")

    def forget() -> None:
        with svc.db.claim_session() as s:
            cal = s.get(TargetRigCalibrationRecord, cal_id)
            if cal is None:
                raise Problem(404, "not-found",
                              f"target rig calibration {cal_id!r} does not exist")
            _busy(s, [cal_id], f"calibration {cal_id}")
            s.delete(cal)

    svc.space.retrying(forget)
    _remove_folders(svc, [cal_id])
    return Response(status_code=204)
