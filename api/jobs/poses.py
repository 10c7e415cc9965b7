"""Pose jobs: capture on a rig (decoded live), decode imported frames, decode stored frames
again. Workers write into the job's staging folder (<data>/tmp/<job>); only this server
moves the finished maps into the pose folder, once the task succeeded."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy.orm import Session

from api.db import PoseRecord
from api.jobs.model import STOPPED_STATES, Job, JobKind
from api.maps_durability import mark_pending
from api.pose_path import (
    CAMERA_SUMMARY,
    MAPS,
    ExecutorDecode,
    ExecutorRigDecode,
    camera_dir,
    camera_dirs,
    capture_live,
    capture_rig_live,
    pose_camera_names,
    stored_indices,
    write_camera_names,
)
from api.rigs import RigHandle
from api.storage import NO_SPACE, pose_bytes
from api.worker.tasks import decode_task, warm_decode_task
from calibration.shared.atomic import write_json_atomic
from calibration.shared.frame_store import FrameStore
from calibration.shared.plan import Plan
from calibration.shared.progress import TaskContext

if TYPE_CHECKING:
    from api.services import Services


def decode_staged(svc: Services, ctx: TaskContext, plan_path: Path, frames: Path,
                  pose_dir: Path, **task_kwargs: Any) -> dict[str, Any]:
    """Decode `frames` on the executor into the job's staging folder and wait (cancel
    propagates); on success move maps.npz into `pose_dir`."""
    with svc.store.staging(ctx.job_id) as staged:
        fut = svc.executor.run_task(decode_task, str(plan_path), str(frames),
                                    str(staged / "maps.npz"), job_id=ctx.job_id,
                                    on_progress=ctx.progress, **task_kwargs)
        result = fut.result()
        ctx.check_cancelled()
        svc.store.commit(staged, ["maps.npz"], pose_dir)
    return result


def set_pose_status(svc: Services, pose_id: str, status: str) -> None:
    """Show where a pose's job is (capturing, decoding) on the pose."""
    with svc.db.session() as s:
        s.get(PoseRecord, pose_id).status = status


@dataclass(kw_only=True)
class PoseJob(Job):
    """A job that makes a pose's maps; the pose shows its outcome."""

    svc: Services
    pose_id: str
    #: the pose folder, whose stored frames are the pose's progress when the job stops early
    frames_dir: Path | None = None

    def __post_init__(self) -> None:
        self.resource = f"/sessions/{self.session_id}/poses/{self.pose_id}"
        self.claims = (self.pose_id,)

    def succeeded(self, s: Session, result: dict[str, Any]) -> None:
        p = s.get(PoseRecord, self.pose_id)
        dec = result.get("decode", {})
        flagged = result.get("capture", {}).get("flagged")
        # a pose that failed its integrity check keeps its maps but is not used by default
        if flagged:
            p.status, p.error = "flagged", f"integrity check: {flagged}"
        else:
            p.status, p.error = "ready", None
        p.valid_pixels = dec.get("valid_pixels")
        p.width, p.height = dec.get("width"), dec.get("height")
        p.frames_done = result.get("frames", p.frames_done)

    def ended(self, s: Session, status: str, error: str) -> None:
        p = s.get(PoseRecord, self.pose_id)
        # a pose cut off by a full disk keeps its frames and resumes once there is space
        stopped = status in STOPPED_STATES or error.startswith(NO_SPACE)
        p.status = (status if status in STOPPED_STATES else "interrupted") if stopped \
            else "failed"
        p.error = error
        if self.frames_dir is not None:
            p.frames_done = len(stored_indices(self.frames_dir))


@dataclass(kw_only=True)
class CaptureJob(PoseJob):
    """Capture a pose into its frame store while a worker decodes the stored frames live."""

    kind = JobKind.CAPTURE
    rig_id: str
    plan: Plan
    screen_pose: dict[str, Any] | None = None
    noise_dn: float | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        self.frames_dir = self.svc.store.dir_for(self.pose_id, create=False)

    def bytes_needed(self) -> int:
        """Disk the capture will take: the frame stores (allocated whole at the first frame,
        so a resume needs none) and the maps, for the rig's cameras as configured now."""
        rig = self.svc.rigs.handle(self.rig_id).rig
        several = len(rig.cameras) > 1
        need = 0
        for name, camera in rig.cameras.items():
            info = camera.info
            folder = self.frames_dir if not several or self.frames_dir is None \
                else camera_dirs(self.frames_dir, [name])[name]
            stored = folder is not None and FrameStore(folder).exists()
            need += pose_bytes(0 if stored else len(self.plan.frames), info.width, info.height,
                               info.bit_depth)
        return need

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        handle = self.svc.rigs.handle(self.rig_id)
        if len(handle.rig.cameras) > 1:
            return self.run_cameras(ctx, handle)
        svc, plan = self.svc, self.plan
        pose_dir = svc.store.dir_for(self.pose_id)
        plan_path = svc.store.dir_for(self.session_id or "") / "plan.json"
        handle = svc.rigs.handle(self.rig_id)
        ctx.progress(0, len(plan.frames), "waiting for rig")
        meta = {"pose_id": self.pose_id, "session_id": self.session_id,
                "plan_digest": plan.digest(), "camera": handle.rig.camera.info.name}
        with svc.store.staging(ctx.job_id) as staged:
            with handle.lock:
                ctx.check_cancelled()
                set_pose_status(svc, self.pose_id, "capturing")
                if self.screen_pose is not None:
                    handle.move_screen(self.screen_pose)
                # simulated rigs decode like real ones: the noise is the client's noise_dn
                # or is estimated from the residuals (never the simulator's own model)
                decode = ExecutorDecode(
                    svc.executor, ctx, plan_path, pose_dir, staged / "maps.npz",
                    noise=self.noise_dn, meta=meta, durable=False,
                    compiled=True)  # (long-lived workers: kernels at any size)
                # another worker loads the compiled decoder and, once, this camera's sums
                # now, not while a later pose's frames arrive
                info = handle.rig.camera.info
                svc.executor.submit(warm_decode_task, info.width * info.height, str(plan_path),
                                    (info.height, info.width), self.noise_dn)
                try:
                    cap = capture_live(ctx, handle.rig, plan, pose_dir, decode,
                                       on_frame=svc.preview.publisher(self.rig_id))
                finally:
                    svc.preview.capture_ended(self.rig_id)
            set_pose_status(svc, self.pose_id, "decoding")
            dec = decode.result()
            ctx.check_cancelled()
            decoded_at = time.time()
            # the worker wrote the maps without fsync: ready now, durable in the background
            # (the frames already are; api/maps_durability.py says what a crash leaves)
            mark_pending(pose_dir)
            svc.store.commit(staged, ["maps.npz"], pose_dir)
            svc.maps_sync.submit(pose_dir)
            dec["commit_s"] = round(time.time() - decoded_at, 4)
            dec["decoded_at"] = decoded_at  # the server has the worker's result
        return {"capture": cap, "decode": dec, "frames": len(stored_indices(pose_dir))}

    def run_cameras(self, ctx: TaskContext, handle: RigHandle) -> dict[str, Any]:
        """A pose of a several-camera rig: every camera captured in sync into its own
        folder (`cameras/<name>/`), each decoded live; each camera's maps are made durable
        after the pose is ready, as a one-camera pose's (api/maps_durability.py)."""
        svc, plan, rig = self.svc, self.plan, handle.rig
        pose_dir = svc.store.dir_for(self.pose_id)
        plan_path = svc.store.dir_for(self.session_id or "") / "plan.json"
        names = list(rig.cameras)
        before = pose_camera_names(pose_dir)
        if before and before != names:
            raise RuntimeError(f"the pose was captured with cameras {before}; the rig now has "
                               f"{names}: capture a new pose")
        write_camera_names(pose_dir, names)
        dirs = camera_dirs(pose_dir, names)
        ctx.progress(0, len(plan.frames) * len(names), "waiting for rig")
        with svc.store.staging(ctx.job_id) as staged:
            outs = {name: staged / name / "maps.npz" for name in names}
            for out in outs.values():
                out.parent.mkdir(exist_ok=True)
            with handle.lock:
                ctx.check_cancelled()
                set_pose_status(svc, self.pose_id, "capturing")
                if self.screen_pose is not None:
                    handle.move_screen(self.screen_pose)
                metas = {name: {"pose_id": self.pose_id, "session_id": self.session_id,
                                "plan_digest": plan.digest(), "camera": cam.info.name,
                                "camera_name": name}
                         for name, cam in rig.cameras.items()}
                decode = ExecutorRigDecode(
                    svc.executor, ctx, plan_path,
                    {name: (dirs[name], outs[name]) for name in names}, metas,
                    noise=self.noise_dn, durable=False, compiled=True)
                # another worker loads the compiled decoder and, once, the sums and maps
                # buffers of the rig's most common camera size, a set per such camera
                shapes = Counter((c.info.height, c.info.width) for c in rig.cameras.values())
                (h, w), count = shapes.most_common(1)[0]
                svc.executor.submit(warm_decode_task, h * w, str(plan_path), (h, w),
                                    self.noise_dn, count, resident_maps=True)
                try:
                    cap = capture_rig_live(ctx, rig, plan, dirs, decode,
                                           on_frame=svc.preview.publisher(self.rig_id))
                finally:
                    svc.preview.capture_ended(self.rig_id)
            set_pose_status(svc, self.pose_id, "decoding")
            decs = decode.result()
            ctx.check_cancelled()
            decoded_at = time.time()
            for name in names:  # the maps unsynced: ready now, durable in the background
                mark_pending(dirs[name])
                svc.store.commit(outs[name].parent, ["maps.npz"], dirs[name])
                write_json_atomic(dirs[name] / CAMERA_SUMMARY,
                                  {k: decs[name].get(k) for k in
                                   ("valid_pixels", "width", "height")})
                svc.maps_sync.submit(dirs[name])
        reference = decs[names[0]]
        dec = {"valid_pixels": reference.get("valid_pixels"), "width": reference.get("width"),
               "height": reference.get("height"), "cameras": decs,
               "commit_s": round(time.time() - decoded_at, 4), "decoded_at": decoded_at}
        return {"capture": cap, "decode": dec, "frames": len(stored_indices(pose_dir))}


@dataclass(kw_only=True)
class ImportDecodeJob(PoseJob):
    """Decode frames imported into the pose folder (a stack or PNG/TIFF images)."""

    kind = JobKind.DECODE
    frames: Path
    frame_count: int
    meta: dict[str, Any]
    shape: tuple[int, int]
    noise_dn: float | None = None

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        svc = self.svc
        set_pose_status(svc, self.pose_id, "decoding")
        plan_path = svc.store.dir_for(self.session_id or "") / "plan.json"
        dec = decode_staged(svc, ctx, plan_path, self.frames, self.frames.parent,
                            noise=self.noise_dn, meta=self.meta)
        return {"decode": dec, "frames": self.frame_count, "shape": list(self.shape)}


@dataclass(kw_only=True)
class RedecodeJob(Job):
    """Decode a pose's stored frames again with other options; the new maps replace the old
    ones on success, and on failure the pose keeps its maps and state (the job has the error).
    On a several-camera pose it decodes one camera's frames (`camera`) into that camera's
    maps; the pose's valid pixels follow its reference camera, as a capture's do."""

    kind = JobKind.DECODE
    svc: Services
    pose_id: str
    frames: Path
    before: str  # the pose's status when the job was asked for
    noise_dn: float | None = None
    options: dict[str, float] = field(default_factory=dict)
    camera: str | None = None  # one camera of a several-camera pose

    def __post_init__(self) -> None:
        self.resource = f"/sessions/{self.session_id}/poses/{self.pose_id}"
        self.claims = (self.pose_id,)

    def run(self, ctx: TaskContext) -> dict[str, Any]:
        svc = self.svc
        meta = {"pose_id": self.pose_id, "session_id": self.session_id, "redecoded": True,
                "decode_options": {"noise_dn": self.noise_dn, **self.options},
                **({"camera_name": self.camera} if self.camera else {})}
        plan_path = svc.store.dir_for(self.session_id or "") / "plan.json"
        pose_dir = svc.store.dir_for(self.pose_id)
        folder = camera_dir(pose_dir, self.camera)
        dec = decode_staged(svc, ctx, plan_path, self.frames, folder,
                            noise=self.noise_dn, meta=meta, options=dict(self.options))
        if self.camera is not None:
            write_json_atomic(folder / CAMERA_SUMMARY, {
                k: dec.get(k) for k in ("valid_pixels", "width", "height")})
        names = pose_camera_names(pose_dir)
        # a failed pose of several cameras is ready once every camera has its maps again
        complete = all((d / MAPS).is_file() for d in camera_dirs(pose_dir, names).values())
        return {"decode": dec, "camera": self.camera, "complete": complete,
                "reference": self.camera is None or self.camera == names[0]}

    def succeeded(self, s: Session, result: dict[str, Any]) -> None:
        p = s.get(PoseRecord, self.pose_id)
        if self.before != "flagged" and result["complete"]:
            p.status, p.error = "ready", None
        if result["reference"]:
            p.valid_pixels = result["decode"]["valid_pixels"]
