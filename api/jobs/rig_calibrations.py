"""Rig calibration jobs: every camera of a several-camera session's poses fitted jointly on a
worker (api/worker/rig_tasks.py); this server moves rig.json and result.json into the
calibration's folder."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from sqlalchemy.orm import Session

from api.db import CalibrationRecord
from api.jobs.model import Job, JobKind
from api.pose_path import camera_maps_path, pose_camera_names
from api.worker.rig_tasks import RIG_OUTPUTS, rig_calibrate_task
from calibration.shared.progress import TaskContext

if TYPE_CHECKING:
    from api.services import Services


@dataclass(kw_only=True)
class RigCalibrateJob(Job):
    """Fit every camera of the poses jointly: each pose is a view all its cameras share."""

    kind = JobKind.CALIBRATE
    svc: Services
    cal_id: str
    models: dict[str, str]
    pose_ids: list[str]
    heldout_pose_ids: list[str]
    options: dict[str, Any]
    reference: str | None

    def __post_init__(self) -> None:
        self.resource = f"/calibrations/{self.cal_id}"
        self.claims = (self.cal_id,)

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        svc = self.svc
        with svc.db.session() as s:
            s.get(CalibrationRecord, self.cal_id).status = "running"
        plan_path = str(svc.store.dir_for(self.session_id or "") / "plan.json")
        entries = []
        for pid in [*self.pose_ids, *self.heldout_pose_ids]:
            pose_dir = svc.store.dir_for(pid)
            entries += [(cam, pid, "maps", str(camera_maps_path(pose_dir, cam)))
                        for cam in pose_camera_names(pose_dir)]
        with svc.store.staging(ctx.job_id) as staged:
            fut = svc.executor.run_task(rig_calibrate_task, plan_path, entries, self.models,
                                        str(staged), job_id=ctx.job_id,
                                        on_progress=ctx.progress, options=self.options,
                                        heldout_views=self.heldout_pose_ids or None,
                                        reference=self.reference)
            result = fut.result()
            ctx.check_cancelled()
            svc.store.commit(staged, RIG_OUTPUTS, svc.store.dir_for(self.cal_id))
        return result

    def succeeded(self, s: Session, result: dict[str, Any]) -> None:
        c = s.get(CalibrationRecord, self.cal_id)
        c.status, c.stats, c.exports = "succeeded", result.get("stats"), list(RIG_OUTPUTS)

    def ended(self, s: Session, status: str, error: str) -> None:
        c = s.get(CalibrationRecord, self.cal_id)
        c.status, c.error = status, error
