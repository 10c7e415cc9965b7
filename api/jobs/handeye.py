"""The hand-eye job: fit the camera to a session's poses (their maps) or a target session's
views (their observations), then where it sits on (or beside) the robot from the robot pose
of each; the latest result is kept in the session folder as phasecal.handeye/1 (one such
job per session at a time)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from api.jobs.model import Job, JobKind
from calibration import handeye_files
from calibration.shared.atomic import write_json_atomic
from calibration.shared.progress import TaskContext

if TYPE_CHECKING:
    from api.services import Services

RESULT = "handeye.json"


def handeye_task(ctx: TaskContext, mount: str, robot_poses: dict[str, Any], source: str,
                 paths: dict[str, str], plan_path: str | None, model: str, out_path: str,
                 options: dict[str, Any] | None = None) -> dict[str, Any]:
    """On the executor: write the robot poses beside the output, run the hand-eye, write the
    document; returns its summary (the job's result)."""
    robot_path = Path(out_path).with_name("robot-poses.json")
    write_json_atomic(robot_path, robot_poses)
    doc = handeye_files(mount, robot_path, source, paths, model,  # type: ignore[arg-type]
                        plan_path=plan_path, options=options, progress=ctx.progress,
                        cancelled=ctx.cancelled)
    ctx.check_cancelled()
    write_json_atomic(out_path, doc)
    held = doc["heldout"]
    return {"mount": mount, "hand_eye_sigma": doc["stats"]["hand_eye_sigma"],
            "heldout": {k: held[k] for k in ("rms_mm", "rms_deg", "expected_rms_mm",
                                             "expected_rms_deg", "normalized_mean")}}


@dataclass(kw_only=True)
class HandEyeJob(Job):
    """Hand-eye of the views in `paths` (VIEW -> maps.npz with the session's plan, or VIEW ->
    observations.npz) with the robot poses keyed by the same VIEW names."""

    kind = JobKind.HANDEYE  # a camera fit and the hand-eye fit on it
    svc: Services
    mount: str
    model: str
    robot_poses: dict[str, Any]
    source: str  # "maps" or "observations"
    paths: dict[str, str]
    options: dict[str, Any]
    resource_path: str  # the route the result is read at

    def __post_init__(self) -> None:
        self.resource = self.resource_path
        self.claims = (f"{self.session_id}:handeye",)

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        svc = self.svc
        folder = svc.store.dir_for(self.session_id or "")
        plan = str(folder / "plan.json") if self.source == "maps" else None
        with svc.store.staging(ctx.job_id) as staged:  # the worker writes only here
            fut = svc.executor.run_task(handeye_task, self.mount, self.robot_poses,
                                        self.source, self.paths, plan, self.model,
                                        str(staged / RESULT), job_id=ctx.job_id,
                                        on_progress=ctx.progress, options=self.options or None)
            result = fut.result()
            ctx.check_cancelled()
            doc = json.loads((staged / RESULT).read_bytes())
        svc.store.write_bytes(folder / RESULT, json.dumps(doc, indent=1).encode())
        return result
