"""The quick-intrinsics job: closed-form K of a session from its poses' white flats or maps;
the latest result is kept in the session folder (one such job per session at a time)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from api.jobs.model import Job, JobKind
from api.worker.intrinsics_task import intrinsics_task
from calibration.shared.progress import TaskContext

if TYPE_CHECKING:
    from api.services import Services

RESULT = "intrinsics.json"


@dataclass(kw_only=True)
class IntrinsicsJob(Job):
    """Estimate K with `method` from `paths` (flat frame sources or maps, one per pose)."""

    kind = JobKind.INTRINSICS
    svc: Services
    pose_ids: list[str]
    paths: list[str]
    source: str
    method: str
    square_pixels: bool
    zero_skew: bool

    def __post_init__(self) -> None:
        self.resource = f"/sessions/{self.session_id}/intrinsics"
        self.claims = (f"{self.session_id}:intrinsics",)

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        svc = self.svc
        folder = svc.store.dir_for(self.session_id or "")
        with svc.store.staging(ctx.job_id) as staged:  # the worker writes only here
            fut = svc.executor.run_task(intrinsics_task, str(folder / "plan.json"), self.paths,
                                        self.source, self.method, str(staged / RESULT),
                                        job_id=ctx.job_id, on_progress=ctx.progress,
                                        square_pixels=self.square_pixels,
                                        zero_skew=self.zero_skew)
            result = {**fut.result(), "pose_ids": self.pose_ids, "source": self.source}
            ctx.check_cancelled()
        svc.store.write_bytes(folder / RESULT, json.dumps(result, indent=1).encode())
        return result
