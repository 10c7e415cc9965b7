"""Rig calibration jobs from target sessions: each camera's board observations (one target
session per camera), its views paired across cameras by shot name, fitted jointly on a
worker by the same task as a screen session's rig (api/worker/rig_tasks.py); this server
moves rig.json and result.json into the calibration's folder."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from sqlalchemy.orm import Session

from api.db import TargetRigCalibrationRecord
from api.jobs.model import Job, JobKind
from api.worker.rig_tasks import RIG_OUTPUTS, rig_calibrate_task
from calibration.shared.progress import TaskContext

if TYPE_CHECKING:
    from api.services import Services


def shot_entries(svc: Services, cameras: dict[str, dict[str, Any]]
                 ) -> list[tuple[str, str, str, str]]:
    """(camera, shot, "observations", path) of every camera's views: the rig fit's input."""
    return [(cam, shot, "observations", str(svc.store.file(spec["session_id"], f"{vid}.npz")))
            for cam, spec in cameras.items() for shot, vid in spec["views"].items()]


def used_view_ids(rec: TargetRigCalibrationRecord) -> set[str]:
    """Every target view a rig calibration reads."""
    return {vid for spec in rec.cameras.values() for vid in spec["views"].values()}


@dataclass(kw_only=True)
class TargetRigCalibrateJob(Job):
    """Fit every camera's board observations jointly: views of one shot name are one board
    placement that their cameras saw at once."""

    kind = JobKind.CALIBRATE
    svc: Services
    cal_id: str
    cameras: dict[str, dict[str, Any]]
    models: dict[str, str]
    heldout_shots: list[str]
    options: dict[str, Any]
    reference: str

    def __post_init__(self) -> None:
        self.resource = f"/target-rig-calibrations/{self.cal_id}"
        self.claims = (self.cal_id,)

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        svc = self.svc
        with svc.db.session() as s:
            s.get(TargetRigCalibrationRecord, self.cal_id).status = "running"
        with svc.store.staging(ctx.job_id) as staged:
            fut = svc.executor.run_task(rig_calibrate_task, None,
                                        shot_entries(svc, self.cameras), self.models,
                                        str(staged), job_id=ctx.job_id,
                                        on_progress=ctx.progress, options=self.options,
                                        heldout_views=self.heldout_shots or None,
                                        reference=self.reference)
            result = fut.result()
            ctx.check_cancelled()
            svc.store.commit(staged, RIG_OUTPUTS, svc.store.dir_for(self.cal_id))
        return result

    def succeeded(self, s: Session, result: dict[str, Any]) -> None:
        c = s.get(TargetRigCalibrationRecord, self.cal_id)
        c.status, c.stats = "succeeded", result.get("stats")

    def ended(self, s: Session, status: str, error: str) -> None:
        c = s.get(TargetRigCalibrationRecord, self.cal_id)
        c.status, c.error = status, error
