"""Restart safety: resources whose job was interrupted are marked so, with the reason."""

from __future__ import annotations

from sqlalchemy import select

from api.db import CalibrationRecord, Database, PoseRecord


def mark_interrupted(db: Database, job_ids: list[str], reason: str) -> None:
    """Poses and calibrations whose job was cut off become `interrupted` (poses can resume)."""
    if not job_ids:
        return
    with db.session() as s:
        for pose in s.scalars(select(PoseRecord).where(PoseRecord.job_id.in_(job_ids))):
            if pose.status not in ("ready", "failed", "cancelled"):
                pose.status = "interrupted"
                pose.error = reason
        for cal in s.scalars(
            select(CalibrationRecord).where(CalibrationRecord.job_id.in_(job_ids))
        ):
            if cal.status in ("queued", "running"):
                cal.status = "interrupted"
                cal.error = reason
