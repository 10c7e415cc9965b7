"""The auto job: a robot places the camera or the screen, phasecal plans, captures, refits
and stops when the target is met or the pose budget is spent.

Each pose is captured by the capture job's own path (`CaptureJob.run` on this job's context:
the live decode, the pose record and its outcome as a capture of `POST .../poses` has them).
The refit (guidance fit, hand-eye, ranked flange candidates: `calibration.plan_step`) runs
on the executor. A candidate outside the asked workspace, or one the mover refuses, is
skipped and the next best is tried. A cancel stops the mover at once (`Mover.stop`) and
ends the job `cancelled`; the poses captured so far stay. The run's log (poses, skipped
candidates, worst sigma after each pose, hand-eye, stop reason) is kept in the session
folder as auto.json after every step and is the job's result.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import func, select

from acquisition.mover import (
    Mover,
    MoveRefused,
    MoverInfo,
    MoveStopped,
    RobotPose,
    Workspace,
)
from acquisition.rig import Rig
from api.db import PoseRecord
from api.jobs.handeye import RESULT as HANDEYE_RESULT
from api.jobs.model import Job, JobKind
from api.jobs.poses import CaptureJob
from api.store import new_id
from calibration import (
    MIN_HANDEYE_VIEWS,
    MIN_SCREEN_COVERAGE,
    ROBOT_POSES_FORMAT,
    START_STEP_MM,
    START_TURNS,
    covers_screen,
    plan_step,
    probe_moves,
    screen_distance_mm,
    starting_moves,
)
from calibration.shared.maps import load_maps
from calibration.shared.plan import Plan, read_plan
from calibration.shared.progress import Cancelled, TaskContext

if TYPE_CHECKING:
    from api.services import Services

LOG = "auto.json"  # the latest auto run of a session
STOP_POLL_S = 0.02  # how often a move checks for a cancel


def rig_mover(rig: Rig) -> Mover | None:
    """The mover the loop drives: the rig's own."""
    return rig.mover


def auto_plan_task(ctx: TaskContext, plan_path: str, maps_paths: dict[str, str],
                   robot_poses: dict[str, Any], mount: str, model: str) -> dict[str, Any]:
    """On the executor: refit the session's poses and plan the next flange poses
    (`calibration.plan_step`); plain data back."""
    maps = {}
    for pose_id, path in maps_paths.items():
        ctx.check_cancelled()
        maps[pose_id] = load_maps(path)
    step = plan_step(maps, read_plan(plan_path), robot_poses, mount,  # type: ignore[arg-type]
                     model)
    return {"worst_ray_sigma_urad": step.worst_rad * 1e6, "handeye": step.handeye,
            "handeye_sigma": step.handeye_sigma(), "note": step.note,
            "candidates": [c.to_json() for c in step.candidates]}


class PoseContext(TaskContext):
    """The auto job's context as one pose's capture sees it: the job's cancel, and the
    capture's progress shown as the stage of the pose being taken."""

    def __init__(self, outer: TaskContext, label: str, done: int, total: int) -> None:
        super().__init__(outer.job_id, on_progress=lambda d, t, stage: outer.progress(
            done, total, f"{label}: {stage} {d}/{t}"))
        self.outer = outer

    def cancelled(self) -> bool:
        return self.outer.cancelled()


@dataclass
class AutoLoop:
    """The loop itself, for the service's job and the CLI alike: they differ in where a
    pose is captured (`capture`: a pose at the robot's current pose, its name back), where
    the refit runs and its hand-eye is kept (`refit`: `auto_plan_task`'s result for the
    robot poses so far), where a pose's maps are (`maps_path`) and where the log goes
    (`save`)."""

    rig: Rig
    mount: str
    model: str
    budget: int
    target_urad: float
    capture: Callable[[TaskContext], str]
    refit: Callable[[TaskContext, dict[str, Any]], dict[str, Any]]
    save: Callable[[dict[str, Any]], None]
    maps_path: Callable[[str], Path]
    target_handeye_mm: float | None = None
    target_handeye_mrad: float | None = None
    workspace: Workspace | None = None
    log: dict[str, Any] = field(default_factory=dict)
    robot: dict[str, dict[str, Any]] = field(default_factory=dict)  # pose -> flange pose

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        """Starting moves, then refit and the best reachable planned pose, until the target
        is met, the budget spent or no reachable pose helps; the log. A cancel is logged
        (`stop_reason` "cancelled") and raised."""
        try:
            return self.loop(ctx)
        except Cancelled:
            self.stop("cancelled")
            raise

    def loop(self, ctx: TaskContext) -> dict[str, Any]:
        mover = rig_mover(self.rig)
        if mover is None:
            raise RuntimeError("the rig has no mover: add a `mover` section to its config")
        self.log = {"mount": self.mount, "model": self.model, "budget": self.budget,
                    "target": self.target(), "mover": mover.info.name, "poses": [],
                    "skipped": [], "moving_to": None, "handeye": None,
                    "worst_ray_sigma_urad": None, "stop_reason": None}
        self.starting_set(ctx, mover.current_pose())
        while True:
            if len(self.robot) < MIN_HANDEYE_VIEWS:
                return self.stop(f"only {len(self.robot)} of the {MIN_HANDEYE_VIEWS} starting "
                                 "poses could be taken: move the robot where the camera sees "
                                 "the whole screen, with room to turn, and start again")
            step = self.refit_now(ctx, mover.info)
            if self.met(step):
                return self.stop("target met")
            if len(self.robot) >= self.budget:
                return self.stop("budget spent")
            if not self.next_pose(ctx, step["candidates"]):
                return self.stop("no reachable pose lowers the worst ray sigma further")

    def starting_set(self, ctx: TaskContext, current: RobotPose) -> None:
        """The pose the robot stands in and a step back (`probe_moves`), then turns about
        the screen (`starting_moves`) until `MIN_HANDEYE_VIEWS` poses show it; a turn whose
        capture lost the screen is dropped from the loop (logged as skipped; its capture
        stays)."""
        for move in probe_moves(current.rotation, current.translation_mm):
            flange = RobotPose(move.flange.rotation, move.flange.translation)
            if not (self.take(ctx, flange, move.reason, None) and self.shows_screen()):
                return
        before, after = (load_maps(self.maps_path(p["pose_id"])) for p in self.log["poses"])
        try:
            distance = screen_distance_mm(before, after, self.rig.screen, START_STEP_MM)
        except ValueError as exc:
            self.log["note"] = f"no starting turns: {exc}"
            return
        pivot = distance if self.mount == "eye-in-hand" else 0.0
        for move in starting_moves(current.rotation, current.translation_mm,
                                   len(START_TURNS), pivot, distance):
            if len(self.robot) >= min(MIN_HANDEYE_VIEWS, self.budget):
                return
            flange = RobotPose(move.flange.rotation, move.flange.translation)
            if self.take(ctx, flange, move.reason, None):
                self.shows_screen()

    def shows_screen(self) -> bool:
        """Whether the last pose's capture shows the screen; if not, the pose is dropped
        from the loop and logged as skipped."""
        entry = self.log["poses"][-1]
        if covers_screen(load_maps(self.maps_path(entry["pose_id"]))):
            return True
        self.log["poses"].pop()
        del self.robot[entry["pose_id"]]
        self.log["skipped"].append({**entry, "why": "the capture lost the screen (under "
                                    f"{MIN_SCREEN_COVERAGE:.0%} of the image decoded)"})
        self.save(self.log)
        return False

    def target(self) -> dict[str, float]:
        out = {"worst_ray_sigma_urad": self.target_urad}
        if self.target_handeye_mm is not None:
            out["handeye_sigma_mm"] = self.target_handeye_mm
        if self.target_handeye_mrad is not None:
            out["handeye_sigma_mrad"] = self.target_handeye_mrad
        return out

    def met(self, step: dict[str, Any]) -> bool:
        sigma = step["handeye_sigma"] or {}
        return bool(step["worst_ray_sigma_urad"] <= self.target_urad
                    and (self.target_handeye_mm is None
                         or sigma.get("translation_mm", float("inf")) <= self.target_handeye_mm)
                    and (self.target_handeye_mrad is None
                         or sigma.get("rotation_mrad", float("inf"))
                         <= self.target_handeye_mrad))

    def next_pose(self, ctx: TaskContext, candidates: list[dict[str, Any]]) -> bool:
        """Take the best candidate the robot can reach (skipping the others); False when
        none can be reached."""
        for cand in candidates:
            flange = RobotPose.from_json(cand["flange"], "candidate")
            reason = (f"planned: {cand['placement']}, predicted worst ray sigma "
                      f"{cand['predicted_worst_ray_sigma_urad']:.3g} urad")
            if self.take(ctx, flange, reason, cand):
                return True
        return False

    def take(self, ctx: TaskContext, flange: RobotPose, reason: str,
             cand: dict[str, Any] | None) -> bool:
        """Move to `flange` and capture a pose there; False (and a skipped entry) when the
        workspace or the mover refuses the pose, or the budget is spent."""
        if len(self.robot) >= self.budget:
            return False
        number = len(self.robot) + 1
        entry: dict[str, Any] = {"flange": flange.to_json(), "reason": reason,
                                 "predicted_worst_ray_sigma_urad":
                                 cand and cand["predicted_worst_ray_sigma_urad"]}
        why = None if self.workspace is None else self.workspace.why_unreachable(flange)
        label = f"pose {number}/{self.budget}"
        if why is None:
            predicted = "" if cand is None else \
                f" (predicted {cand['predicted_worst_ray_sigma_urad']:.3g} urad)"
            self.log["moving_to"] = entry  # the planned pose, readable while the robot moves
            self.save(self.log)
            ctx.progress(number - 1, self.budget, f"{label}: moving{predicted}")
            try:
                reached = self.move(ctx, flange)
            except MoveRefused as exc:
                why = str(exc)
            self.log["moving_to"] = None  # (kept when a cancel stops the move: where it went)
        if why is not None:
            self.log["skipped"].append({**entry, "why": why})
            self.save(self.log)
            return False
        name = self.capture(PoseContext(ctx, label, number - 1, self.budget))
        self.robot[name] = reached.to_json()
        self.log["poses"].append({"pose_id": name, **entry, "reached": reached.to_json(),
                                  "worst_ray_sigma_urad": None})
        self.save(self.log)
        ctx.progress(number, self.budget, f"{label}: captured")
        return True

    def move(self, ctx: TaskContext, flange: RobotPose) -> RobotPose:
        """`rig.move_to`, stopped at once (`Mover.stop`) when the job is cancelled."""
        done = threading.Event()
        mover = self.rig.mover

        def watch() -> None:
            while not done.wait(STOP_POLL_S):
                if ctx.cancelled() and mover is not None:
                    mover.stop()
                    return

        watcher = threading.Thread(target=watch, name="auto-stop", daemon=True)
        watcher.start()
        try:
            return self.rig.move_to(flange)
        except MoveStopped:
            ctx.check_cancelled()
            raise
        finally:
            done.set()
            watcher.join()

    def refit_now(self, ctx: TaskContext, info: MoverInfo) -> dict[str, Any]:
        """Refit on the poses so far; the log takes the worst sigma and the hand-eye."""
        ctx.progress(len(self.robot), self.budget, f"refit on {len(self.robot)} poses")
        step = self.refit(ctx, {"format": ROBOT_POSES_FORMAT, "poses": self.robot,
                                "repeatability": {"mm": info.repeatability_mm,
                                                  "deg": info.repeatability_deg}})
        ctx.check_cancelled()
        if step["handeye"] is not None:
            self.log["handeye"] = {"hand_eye": step["handeye"]["hand_eye"],
                                   "sigma": step["handeye_sigma"],
                                   "heldout_rms_mm": step["handeye"]["heldout"].get("rms_mm")}
        self.log["poses"][-1]["worst_ray_sigma_urad"] = step["worst_ray_sigma_urad"]
        self.log["worst_ray_sigma_urad"] = step["worst_ray_sigma_urad"]
        self.log["note"] = step["note"]
        self.save(self.log)
        return step

    def stop(self, reason: str) -> dict[str, Any]:
        self.log["stop_reason"] = reason
        self.save(self.log)
        return self.log


@dataclass(kw_only=True)
class AutoJob(Job):
    """The loop on the session's rig as a job: each pose a capture of the session, the
    refit on the executor, the hand-eye and the log kept in the session folder."""

    kind = JobKind.AUTO
    svc: Services
    rig_id: str
    plan: Plan
    mount: str
    model: str
    budget: int
    target_urad: float
    target_handeye_mm: float | None = None
    target_handeye_mrad: float | None = None
    workspace: Workspace | None = None
    noise_dn: float | None = None

    def __post_init__(self) -> None:
        self.resource = f"/sessions/{self.session_id}/auto"
        self.claims = (f"{self.session_id}:auto",)
        self.total = self.budget

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        loop = AutoLoop(self.svc.rigs.handle(self.rig_id).rig, self.mount, self.model,
                        self.budget, self.target_urad, self.capture, self.refit, self.save,
                        lambda pose_id: self.svc.store.file(pose_id, "maps.npz"),
                        self.target_handeye_mm, self.target_handeye_mrad, self.workspace)
        return loop.run(ctx)

    def capture(self, ctx: TaskContext) -> str:
        """One pose by the capture job's path, recorded as a capture of this session."""
        svc = self.svc
        ctx.check_cancelled()
        cap = CaptureJob(svc=svc, session_id=self.session_id, pose_id=new_id("pose"),
                         rig_id=self.rig_id, plan=self.plan, noise_dn=self.noise_dn)
        svc.space.require(cap.bytes_needed(), f"a capture on rig {self.rig_id}")
        with svc.db.claim_session() as s:
            last = s.scalar(select(func.max(PoseRecord.index))
                            .where(PoseRecord.session_id == self.session_id))
            s.add(PoseRecord(id=cap.pose_id, session_id=self.session_id,
                             index=0 if last is None else int(last) + 1, source="capture",
                             status="pending", job_id=ctx.job_id, frames_done=0,
                             created_at=time.time()))
        try:
            result = cap.run(ctx)
        except BaseException as exc:
            with svc.db.session() as s:
                cap.ended(s, "cancelled" if isinstance(exc, Cancelled) else "failed", str(exc))
            raise
        with svc.db.session() as s:
            cap.succeeded(s, result)
        return cap.pose_id

    def refit(self, ctx: TaskContext, robot: dict[str, Any]) -> dict[str, Any]:
        """Refit on the executor; the latest hand-eye is kept as the session's."""
        svc = self.svc
        folder = svc.store.dir_for(self.session_id or "")
        step = svc.executor.run_task(
            auto_plan_task, str(folder / "plan.json"),
            {p: str(svc.store.file(p, "maps.npz")) for p in robot["poses"]}, robot,
            self.mount, self.model, job_id=ctx.job_id).result()
        if step["handeye"] is not None:
            svc.store.write_bytes(folder / HANDEYE_RESULT,
                                  json.dumps(step["handeye"], indent=1).encode())
        return step

    def save(self, log: dict[str, Any]) -> None:
        """The log so far, in the session folder (a cancelled run keeps it)."""
        path: Path = self.svc.store.dir_for(self.session_id or "") / LOG
        self.svc.store.write_bytes(path, json.dumps(log, indent=1).encode())
