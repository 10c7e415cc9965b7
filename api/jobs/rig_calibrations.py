"""Rig calibration jobs: every camera of a several-camera session's poses fitted jointly on a
worker (api/worker/rig_tasks.py); this server moves rig.json and result.json into the
calibration's folder and draws the rig's report as the job's last step (a report that cannot
be drawn does not fail the fit: its first request draws it again)."""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy.orm import Session

from api.db import CalibrationRecord, RigRecord, SessionRecord
from api.jobs.model import Job, JobKind
from api.pose_path import camera_maps_path, pose_camera_names
from api.problems import Problem
from api.version import phasecal_version
from api.worker.rig_tasks import RIG_OUTPUTS, rig_calibrate_task
from calibration import ReportHeader, RigReportInputs, draw_rig_report, load_rig, rig_downloads
from calibration.shared.progress import TaskContext

if TYPE_CHECKING:
    from api.services import Services

RIG_REPORT_DIR = "report"
log = logging.getLogger("phasecal.reports")


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
        return fit_rig(svc, ctx, self.cal_id, plan_path, entries, self.models, self.options,
                       self.heldout_pose_ids, self.reference,
                       lambda: draw_rig_report_now(svc, self.cal_id))

    def succeeded(self, s: Session, result: dict[str, Any]) -> None:
        c = s.get(CalibrationRecord, self.cal_id)
        c.status, c.stats, c.exports = "succeeded", result.get("stats"), list(RIG_OUTPUTS)

    def ended(self, s: Session, status: str, error: str) -> None:
        c = s.get(CalibrationRecord, self.cal_id)
        c.status, c.error = status, error


def fit_rig(svc: Services, ctx: TaskContext, cal_id: str, plan_path: str | None,
            entries: list[tuple[str, str, str, str]], models: dict[str, str],
            options: dict[str, Any], heldout: list[str], reference: str | None,
            draw_report: Callable[[], Path]) -> dict[str, Any]:
    """A rig's joint fit on a worker (`rig_calibrate_task` over `entries`), its files moved
    into calibration `cal_id`'s folder, then its report drawn (`draw_report`); a report
    that cannot be drawn does not fail the fit: its first request draws it again."""
    with svc.store.staging(ctx.job_id) as staged:
        fut = svc.executor.run_task(rig_calibrate_task, plan_path, entries, models,
                                    str(staged), job_id=ctx.job_id, on_progress=ctx.progress,
                                    options=options, heldout_views=heldout or None,
                                    reference=reference)
        result = fut.result()
        ctx.check_cancelled()
        svc.store.commit(staged, RIG_OUTPUTS, svc.store.dir_for(cal_id))
    try:
        draw_report()
    except Exception as exc:  # whatever went wrong, the fit stands
        log.warning("calibration %s: rig report not drawn: %s", cal_id, exc)
    return result


def rig_report_inputs(svc: Services, rec: CalibrationRecord) -> RigReportInputs:
    """What a rig calibration's report is drawn from: its stored files and its record."""
    cal_dir = svc.store.dir_for(rec.id)
    maps: dict[str, list[str]] = {}
    for pid in rec.pose_ids:
        pose_dir = svc.store.dir_for(pid)
        for cam in pose_camera_names(pose_dir):
            path = camera_maps_path(pose_dir, cam)
            if path.is_file():
                maps.setdefault(cam, []).append(str(path))
    with svc.db.session() as s:
        ses = s.get(SessionRecord, rec.session_id)
        session = f"{ses.name or 'unnamed'} ({rec.session_id})" if ses else rec.session_id
        rig = s.get(RigRecord, ses.rig_id) if ses is not None and ses.rig_id else None
        rig_text = (f"{rig.name} ({rig.id}, {rig.config.get('kind', 'simulated')})" if rig
                    else "none")
    models = (rec.options or {}).get("rig", {}).get("camera_models", {})
    header = ReportHeader(
        title=f"Rig calibration {rec.id}", session=session, rig=rig_text,
        cameras=", ".join(f"{c} ({m})" for c, m in models.items()) or "not recorded",
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(rec.created_at)),
        software=f"phasecal {phasecal_version()}", poses_used=list(rec.pose_ids),
        heldout=list(rec.heldout_pose_ids))
    rig_json = cal_dir / "rig.json"
    return RigReportInputs(str(rig_json), str(cal_dir / "result.json"), maps, header,
                           rig_downloads(load_rig(rig_json), rec.id))


def draw_rig_report_now(svc: Services, cal_id: str) -> Path:
    """Draw a rig calibration's report on the executor, wait, move it into place; its folder."""
    with svc.db.session() as s:
        rec = s.get(CalibrationRecord, cal_id)
    return draw_report_into(svc, cal_id, rig_report_inputs(svc, rec))


def draw_report_into(svc: Services, cal_id: str, inputs: RigReportInputs) -> Path:
    """Draw a rig report from `inputs` on the executor, wait, move it into calibration
    `cal_id`'s folder (screen-session and target-session rigs alike); its folder."""
    tmp = svc.store.temp_dir()
    try:
        svc.executor.submit(draw_rig_report, inputs, str(tmp)).result()
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    final = svc.store.dir_for(cal_id) / RIG_REPORT_DIR
    svc.store.replace_dir(tmp, final)
    return final


def is_rig_calibration(rec: CalibrationRecord) -> bool:
    """Whether a calibration record is of a rig (its options name the cameras' models)."""
    return "rig" in (rec.options or {})


def rig_report_folder(svc: Services, rec: CalibrationRecord) -> Path | None:
    """The folder of a rig calibration's report; None while the fit runs. Drawn here when
    the job could not draw it."""
    return report_folder(svc, rec.id, rec.status, lambda: draw_rig_report_now(svc, rec.id))


def report_folder(svc: Services, cal_id: str, status: str, draw: Callable[[], Path]
                  ) -> Path | None:
    """The folder of rig calibration `cal_id`'s report (`status`: its record's); None while
    the fit runs, a 409 unless it succeeded; drawn by `draw` when missing."""
    if status in ("queued", "running"):
        return None
    if status != "succeeded":
        raise Problem(409, "not-ready", f"calibration {cal_id} is {status}; a report "
                      "exists only for a calibration that succeeded")
    folder = svc.store.dir_for(cal_id) / RIG_REPORT_DIR
    if (folder / "report.html").is_file():
        return folder
    return draw()
