"""Rig calibration jobs from target sessions: each camera's board observations (one target
session per camera), its views paired across cameras by shot name, fitted jointly on a
worker by the same task as a screen session's rig (api/worker/rig_tasks.py); this server
moves rig.json and result.json into the calibration's folder and draws the rig's report as
the job's last step, its coverage from each camera's observation files (a report that
cannot be drawn does not fail the fit: its first request draws it again)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy.orm import Session

from api.db import TargetRigCalibrationRecord, TargetSessionRecord
from api.jobs.model import Job, JobKind
from api.jobs.rig_calibrations import draw_report_into, fit_rig, report_folder
from api.version import phasecal_version
from calibration import ReportHeader, RigReportInputs, load_rig, rig_downloads
from calibration.shared.progress import TaskContext

if TYPE_CHECKING:
    from api.services import Services

TARGET_RIG_COLLECTION = "/target-rig-calibrations"


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
        self.resource = f"{TARGET_RIG_COLLECTION}/{self.cal_id}"
        self.claims = (self.cal_id,)

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        svc = self.svc
        with svc.db.session() as s:
            s.get(TargetRigCalibrationRecord, self.cal_id).status = "running"
        return fit_rig(svc, ctx, self.cal_id, None, shot_entries(svc, self.cameras),
                       self.models, self.options, self.heldout_shots or [], self.reference,
                       lambda: draw_target_rig_report_now(svc, self.cal_id))

    def succeeded(self, s: Session, result: dict[str, Any]) -> None:
        c = s.get(TargetRigCalibrationRecord, self.cal_id)
        c.status, c.stats = "succeeded", result.get("stats")

    def ended(self, s: Session, status: str, error: str) -> None:
        c = s.get(TargetRigCalibrationRecord, self.cal_id)
        c.status, c.error = status, error


def target_rig_report_inputs(svc: Services, rec: TargetRigCalibrationRecord) -> RigReportInputs:
    """What a target rig calibration's report is drawn from: rig.json, result.json and each
    camera's observation files of the training shots (those still stored)."""
    cal_dir = svc.store.dir_for(rec.id)
    held = set(rec.heldout_shots or [])
    observations: dict[str, list[str]] = {}
    for cam, spec in rec.cameras.items():
        ses_dir = svc.store.dir_for(spec["session_id"], create=False)  # it may be gone
        for shot, vid in spec["views"].items():
            path = ses_dir / f"{vid}.npz"
            if shot not in held and path.is_file():
                observations.setdefault(cam, []).append(str(path))
    with svc.db.session() as s:
        names = {cam: s.get(TargetSessionRecord, spec["session_id"])
                 for cam, spec in rec.cameras.items()}
        sessions = "; ".join(
            f"{cam}: {ses.name or 'unnamed'} ({rec.cameras[cam]['session_id']})" if ses
            else f"{cam}: {rec.cameras[cam]['session_id']} (deleted)"
            for cam, ses in names.items())
        target = next((ses.target for ses in names.values() if ses is not None), None)
    shots = list(dict.fromkeys(shot for spec in rec.cameras.values() for shot in spec["views"]))
    header = ReportHeader(
        title=f"Rig calibration {rec.id}", session=sessions,
        rig=f"board observations, target {target}" if target else "board observations",
        cameras=", ".join(f"{c} ({m})" for c, m in rec.camera_models.items()),
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(rec.created_at)),
        software=f"phasecal {phasecal_version()}",
        poses_used=[shot for shot in shots if shot not in held],
        heldout=list(rec.heldout_shots or []))
    rig_json = cal_dir / "rig.json"
    return RigReportInputs(str(rig_json), str(cal_dir / "result.json"), {}, header,
                           rig_downloads(load_rig(rig_json), rec.id, TARGET_RIG_COLLECTION),
                           observations=observations)


def draw_target_rig_report_now(svc: Services, cal_id: str) -> Path:
    """Draw a target rig calibration's report on the executor, wait, move it into place;
    its folder."""
    with svc.db.session() as s:
        rec = s.get(TargetRigCalibrationRecord, cal_id)
    return draw_report_into(svc, cal_id, target_rig_report_inputs(svc, rec))


def target_rig_report_folder(svc: Services, rec: TargetRigCalibrationRecord) -> Path | None:
    """The folder of a target rig calibration's report; None while the fit runs. Drawn here
    when the job could not draw it."""
    return report_folder(svc, rec.id, rec.status,
                         lambda: draw_target_rig_report_now(svc, rec.id))
