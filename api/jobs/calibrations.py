"""Calibration jobs: one model on a session's poses, or a batch of sessions x model settings
spread over the executor. Workers write into the job's staging folder (<data>/tmp/<job>);
this server moves each finished calibration's files into its folder."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from sqlalchemy.orm import Session

from api.db import CalibrationRecord
from api.jobs.model import Job, JobKind
from api.reports import draw_in_job
from api.worker.dask_batch import BatchItem, run_batch
from api.worker.tasks import calibrate_task
from calibration.shared.progress import TaskContext

if TYPE_CHECKING:
    from api.services import Services


def output_names(result: dict[str, Any]) -> list[str]:
    """The files a calibration task wrote: model, result and its exports."""
    return ["model.json", "result.json", *result.get("exports", [])]


def _set_running(svc: Services, cal_ids: list[str]) -> None:
    with svc.db.session() as s:
        for cid in cal_ids:
            s.get(CalibrationRecord, cid).status = "running"


@dataclass(kw_only=True)
class CalibrateJob(Job):
    """Fit one model to a session's poses (optionally scoring held-out poses)."""

    kind = JobKind.CALIBRATE
    svc: Services
    cal_id: str
    model: str
    pose_ids: list[str]
    heldout_pose_ids: list[str]
    options: dict[str, Any]

    def __post_init__(self) -> None:
        self.resource = f"/calibrations/{self.cal_id}"
        self.claims = (self.cal_id,)

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        svc = self.svc
        _set_running(svc, [self.cal_id])
        plan_path = str(svc.store.dir_for(self.session_id or "") / "plan.json")
        maps = [str(svc.store.file(p, "maps.npz")) for p in self.pose_ids]
        heldout = [str(svc.store.file(p, "maps.npz")) for p in self.heldout_pose_ids]
        with svc.store.staging(ctx.job_id) as staged:
            fut = svc.executor.run_task(calibrate_task, plan_path, maps, self.model,
                                        str(staged), job_id=ctx.job_id,
                                        on_progress=ctx.progress, options=self.options,
                                        heldout_paths=heldout or None)
            result = fut.result()
            ctx.check_cancelled()
            svc.store.commit(staged, output_names(result), svc.store.dir_for(self.cal_id))
        draw_in_job(svc, [self.cal_id])  # on the executor: the report's first open is a read
        return result

    def succeeded(self, s: Session, result: dict[str, Any]) -> None:
        c = s.get(CalibrationRecord, self.cal_id)
        c.status, c.stats, c.exports = "succeeded", result.get("stats"), output_names(result)

    def ended(self, s: Session, status: str, error: str) -> None:
        c = s.get(CalibrationRecord, self.cal_id)
        c.status, c.error = status, error


@dataclass(frozen=True)
class BatchEntry:
    """One calibration of a batch: a session's poses with one model setting."""

    cal_id: str
    session_id: str
    pose_ids: tuple[str, ...]
    model: str
    options: dict[str, Any]


@dataclass(kw_only=True)
class BatchCalibrateJob(Job):
    """Calibrate sessions x model settings as sub-tasks; each calibration ends `succeeded` or
    `failed` with its own reason, and cancelling the job cancels every one still running."""

    kind = JobKind.CALIBRATE
    svc: Services
    entries: list[BatchEntry]
    resource: str | None = "/calibrations"

    def __post_init__(self) -> None:
        self.claims = tuple(e.cal_id for e in self.entries)
        self.total = len(self.entries)

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        svc = self.svc
        _set_running(svc, [e.cal_id for e in self.entries])
        with svc.store.staging(ctx.job_id) as staged:
            items = [
                BatchItem(name=e.cal_id, plan_path=str(svc.store.dir_for(e.session_id) /
                                                       "plan.json"),
                          maps_paths=tuple(str(svc.store.file(p, "maps.npz")) for p in e.pose_ids),
                          model=e.model, out_dir=str(staged / e.cal_id), options=e.options)
                for e in self.entries
            ]
            result = run_batch(svc.executor, items, ctx)
            fitted = []
            for outcome in result.get("items", []):
                if outcome["status"] == "succeeded":
                    cid = outcome["name"]
                    svc.store.commit(staged / cid, output_names(outcome["result"]),
                                     svc.store.dir_for(cid))
                    fitted.append(cid)
                outcome.pop("out_dir", None)
        draw_in_job(svc, fitted)  # every report at once on the executor
        return result

    def succeeded(self, s: Session, result: dict[str, Any]) -> None:
        for outcome in result.get("items", []):
            c = s.get(CalibrationRecord, outcome["name"])
            c.status = outcome["status"]
            if outcome["status"] == "succeeded":
                c.stats = outcome["result"].get("stats")
                c.exports = output_names(outcome["result"])
            else:
                c.error = outcome.get("error")

    def ended(self, s: Session, status: str, error: str) -> None:
        for e in self.entries:
            c = s.get(CalibrationRecord, e.cal_id)
            if c.status in ("queued", "running"):
                c.status, c.error = status, error
