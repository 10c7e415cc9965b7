"""Restart safety: resources whose job was interrupted are marked so, with the reason."""

from __future__ import annotations

from collections.abc import Callable

from sqlalchemy import select

from api.db import (
    CalibrationRecord,
    Database,
    JobRecord,
    PoseRecord,
    TargetRigCalibrationRecord,
)


def mark_interrupted(db: Database, job_ids: list[str], reason: str,
                     frames_on_disk: Callable[[str], int] | None = None) -> None:
    """Poses and calibrations (of screen sessions and target-session rigs) whose job was
    cut off become `interrupted` (poses can resume).

    A cut-off capture's progress (pose `frames_done`, job `done`) is set to the frames
    actually on disk (`frames_on_disk(pose_id)`): the last persisted progress may lag.
    """
    if not job_ids:
        return
    with db.session() as s:
        for pose in s.scalars(select(PoseRecord).where(PoseRecord.job_id.in_(job_ids))):
            if pose.status not in ("ready", "failed", "cancelled"):
                pose.status = "interrupted"
                pose.error = reason
            if pose.source == "capture" and frames_on_disk is not None:
                pose.frames_done = frames_on_disk(pose.id)
                job = s.get(JobRecord, pose.job_id)
                if job is not None and job.kind == "capture" and job.stage == "capture":
                    job.done = pose.frames_done
        for record in (CalibrationRecord, TargetRigCalibrationRecord):
            for cal in s.scalars(select(record).where(record.job_id.in_(job_ids))):
                if cal.status in ("queued", "running"):
                    cal.status = "interrupted"
                    cal.error = reason
