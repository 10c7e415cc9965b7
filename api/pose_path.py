"""The live pose path, in one place: frames from the controller -> the pose's frame store ->
the streaming decode -> maps -> pose ready. `phasecal serve` (a capture job) and
`phasecal capture` both run `capture_live`; `phasecal decode` and a re-decode read a
finished store with the same decoder.

    controller (acquisition.controller.capture_pose)
        -> StoreSink: each accepted frame copied into the FrameStore (frames.npy +
           frames.done, memory-mapped: no encoding or fsync on the capture loop)
        -> LiveDecode: `api.worker.tasks.stream_decode_task` follows the store and folds
           frames in as they arrive (on the service's executor, or a thread of the CLI)
        -> maps.npz laid out before the first frame, written by the decoder's finish
        -> the pose is ready shortly after its last frame

One camera's pose is one run of this path. A rig with several cameras runs it once per
camera, in step: the controller shows each pattern once and hands each camera's frame to
that camera's StoreSink, and each camera's store (`cameras/<name>/` in the pose folder) is
followed by its own decode (`ExecutorRigDecode`: one worker task, a thread per camera, so
every camera decodes during the capture on a pool of any size). A capture cut off by a
cancel, an error or a restart resumes at the missing frames. Poses captured by earlier
versions as `frames/frame_NNNN.png` are moved into the store when resumed.
"""

from __future__ import annotations

import json
import queue
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from acquisition.controller import capture_pose, capture_rig_pose
from acquisition.rig import Rig
from api.worker.executor import Executor
from api.worker.tasks import stream_decode_rig_task, stream_decode_task
from calibration.shared.atomic import write_json_atomic
from calibration.shared.frame_store import FrameStore
from calibration.shared.plan import Plan
from calibration.shared.progress import TaskContext

FRAME_RE = re.compile(r"^frame_(\d{4,6})\.(png|tif|tiff)$")
LEGACY_FRAMES = "frames"  # folder of PNG frames written before the frame store
VERDICT = "integrity.json"  # a flagged capture's integrity verdict, kept with its frames
CAMERAS = "cameras"  # a several-camera pose's folder of cameras, `cameras/<name>/`
CAMERA_ORDER = "cameras.json"  # its cameras' names, the reference first
CAMERA_SUMMARY = "decode.json"  # a camera's decoded size and valid pixels, beside its maps
MAPS = "maps.npz"


def camera_dirs(pose_dir: Path, names: list[str]) -> dict[str, Path]:
    """Each camera's folder (frame store, maps, verdict) of a several-camera pose."""
    return {name: pose_dir / CAMERAS / name for name in names}


def pose_camera_names(pose_dir: Path) -> list[str]:
    """The cameras of a several-camera pose, the reference first ([] for one camera)."""
    try:
        return [str(n) for n in json.loads((pose_dir / CAMERA_ORDER).read_text())]
    except FileNotFoundError:
        return []


def pose_cameras(pose_dir: Path, status: str, error: str | None) -> list[dict[str, Any]] | None:
    """Each camera of a several-camera pose as the API shows it (None for one camera): a
    camera with maps is ready (or flagged by its integrity check), the others are where the
    pose is (`status`, `error`)."""
    names = pose_camera_names(pose_dir)
    if not names:
        return None
    out = []
    for name, folder in camera_dirs(pose_dir, names).items():
        entry: dict[str, Any] = {"name": name, "status": status, "error": error}
        if (folder / MAPS).is_file() and (folder / CAMERA_SUMMARY).is_file():
            verdict = stored_verdict(folder)
            entry.update(json.loads((folder / CAMERA_SUMMARY).read_text()),
                         status="flagged" if verdict else "ready",
                         error=f"integrity check: {verdict}" if verdict else None)
        out.append(entry)
    return out


def camera_dir(pose_dir: Path, camera: str | None) -> Path:
    """The folder of a pose's frames and maps (`camera` None: a one-camera pose's own) or of
    one of its cameras; ValueError naming the cameras when `camera` is missing on a
    several-camera pose or names none of them."""
    names = pose_camera_names(pose_dir)
    if camera is None:
        if names:
            raise ValueError(f"camera: this pose has cameras {names}; name one")
        return pose_dir
    if camera not in names:
        raise ValueError(f"camera: {camera!r} is not a camera of this pose "
                         f"({names or 'it has one camera: leave camera out'})")
    return camera_dirs(pose_dir, [camera])[camera]


def camera_maps_path(pose_dir: Path, camera: str | None) -> Path:
    """The maps file of a pose or of one of its cameras (validated as `camera_dir`)."""
    return camera_dir(pose_dir, camera) / MAPS


def write_camera_names(pose_dir: Path, names: list[str]) -> None:
    """Record a several-camera pose's cameras before its first frame (resumes, reads)."""
    pose_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(pose_dir / CAMERA_ORDER, names)


def stored_verdict(pose_dir: Path) -> str | None:
    """The reason a capture of this pose's frames was flagged, or None: the integrity check
    cannot be repeated once the pose is over, so a resume that only decodes the stored frames
    again (e.g. after maps lost in a power cut) must keep the verdict. A several-camera
    pose's verdict names each flagged camera."""
    names = pose_camera_names(pose_dir)
    if names:
        flagged = {n: v for n, d in camera_dirs(pose_dir, names).items()
                   if (v := stored_verdict(d)) is not None}
        return "; ".join(f"camera {n!r}: {v}" for n, v in flagged.items()) or None
    try:
        return str(json.loads((pose_dir / VERDICT).read_text())["flagged"])
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError) as exc:  # flagged stays flagged
        return f"integrity verdict in {VERDICT} unreadable ({exc})"


def _legacy_indices(folder: Path) -> set[int]:
    if not folder.is_dir():
        return set()
    return {int(m.group(1)) for p in folder.iterdir() if (m := FRAME_RE.match(p.name))}


def stored_indices(pose_dir: Path) -> set[int]:
    """Plan indices already captured for the pose (frame store, or a legacy PNG folder; on
    several cameras, those every camera has)."""
    names = pose_camera_names(pose_dir)
    if names:
        return set.intersection(*(stored_indices(d)
                                  for d in camera_dirs(pose_dir, names).values()))
    store = FrameStore(pose_dir)
    if store.exists():
        return {int(i) for i in store.stored()}
    return _legacy_indices(pose_dir / LEGACY_FRAMES)


def frames_path(pose_dir: Path) -> Path:
    """What `decode_task` reads for a captured pose: the store's .npy or a legacy folder."""
    store = FrameStore(pose_dir)
    return store.frames_path if store.frames_path.is_file() else pose_dir / LEGACY_FRAMES


def _import_legacy(store: FrameStore, pose_dir: Path) -> None:
    """Move a legacy PNG capture's frames into the store (then drop the PNGs)."""
    folder = pose_dir / LEGACY_FRAMES
    for index in sorted(_legacy_indices(folder)):
        path = next(folder.glob(f"frame_{index:04d}.*"))
        store.add(index, cv2.imread(str(path), cv2.IMREAD_UNCHANGED))
    store.flush()
    for p in folder.iterdir():
        p.unlink()
    folder.rmdir()


class StoreSink:
    """A `FrameSink`: stores frames not yet stored, reports progress over the whole plan.

    The copy into the store (5 MB per 5 Mpixel frame, with first-touch page faults) runs in
    a writer thread, in order, so the capture thread never waits for it between a frame and
    the next vsync-bound show or trigger; NumPy's copy releases the GIL. Frames handed over
    are not modified afterwards (as for every `FrameSink`). `close` waits for the writer and
    raises its first error; an error also surfaces at the next `add`.
    """

    def __init__(self, store: FrameStore, ctx: TaskContext, total: int,
                 on_frame: Any = None, report: Callable[[], None] | None = None) -> None:
        self.store, self.ctx, self.total = store, ctx, total
        self.have = {int(i) for i in store.stored()}  # stored or handed to the writer
        self.on_frame = on_frame
        self.report = report  # progress over several cameras' sinks (default: this one's)
        self.store_s = 0.0  # time spent storing frames (writer thread)
        self.last_stored_at: float | None = None  # wall time the newest frame was stored
        self._queue: queue.Queue[tuple[int, np.ndarray] | None] = queue.Queue()
        self._writer: threading.Thread | None = None
        self._error: BaseException | None = None

    def add(self, index: int, image: np.ndarray) -> None:
        if self._error is not None:
            raise self._error
        if index not in self.have:
            if self._writer is None:
                self._writer = threading.Thread(target=self._write_loop, daemon=True,
                                                name="frame-store-writer")
                self._writer.start()
            self.have.add(index)
            self._queue.put((index, image))
        if self.report is not None:
            self.report()
        else:
            self.ctx.progress(len(self.have), self.total, "capture")

    def _write_loop(self) -> None:
        while (item := self._queue.get()) is not None:
            if self._error is not None:
                continue  # drain: the capture side raises the first error
            index, image = item
            t0 = time.perf_counter()
            try:
                self.store.add(index, image)
            except BaseException as exc:
                self._error = exc
                continue
            self.store_s += time.perf_counter() - t0
            self.last_stored_at = time.time()
            if self.on_frame is not None:
                self.on_frame(self.store, index)

    def close(self) -> None:
        """Wait until every frame handed over is in the store; raise the writer's error."""
        if self._writer is not None:
            self._queue.put(None)
            self._writer.join()
            self._writer = None
        if self._error is not None:
            raise self._error


def capture_frames(ctx: TaskContext, rig: Rig, plan: Plan, pose_dir: Path,
                   on_frame: Any = None) -> dict[str, Any]:
    """Run the controller for the plan frames missing from the pose's store (the rig's
    reference camera: a one-camera rig's camera); raise on failure/cancel.
    `on_frame(store, index)` is called after each stored frame."""
    return capture_camera_frames(ctx, rig, plan, {rig.reference: pose_dir}, on_frame)


def capture_camera_frames(ctx: TaskContext, rig: Rig, plan: Plan, dirs: dict[str, Path],
                          on_frame: Any = None) -> dict[str, Any]:
    """Run the controller for the plan frames missing from any of the cameras' stores
    (`dirs`: a folder per camera, named as in `rig.cameras`), each camera's frames into its
    store; raise on failure/cancel. `on_frame(store, index)` follows the first camera's
    stored frames (the live preview)."""
    total = len(plan.frames)
    sinks: dict[str, StoreSink] = {}

    def report() -> None:
        ctx.progress(sum(len(k.have) for k in sinks.values()), total * len(sinks), "capture")

    for name, folder in dirs.items():
        store = FrameStore(folder, total, stage=True)  # read by the live decode
        if (folder / LEGACY_FRAMES).is_dir():
            _import_legacy(store, folder)
        sinks[name] = StoreSink(store, ctx, total, on_frame if not sinks else None,
                                report if len(dirs) > 1 else None)
    several = len(sinks) > 1
    have = min(len(k.have) for k in sinks.values())
    if several:
        report()
    else:
        ctx.progress(have, total, "capture")
    missing = [i for i in range(total) if any(i not in k.have for k in sinks.values())]
    if not missing:
        for k in sinks.values():
            k.store.close()
        verdict = _verdict(dirs, several)
        return {"captured": 0, "resumed_from": have, **({"flagged": verdict} if verdict else {})}
    t0 = time.perf_counter()
    try:
        first, sink = next(iter(sinks.items()))
        if several or first != rig.reference:
            result = capture_rig_pose(rig, plan, sinks, indices=missing, progress=None,
                                      cancelled=ctx.cancelled)
        else:  # (a one-camera rig: the controller's one-camera entry point, as always)
            result = capture_pose(rig, plan, sink, indices=missing, progress=None,
                                  cancelled=ctx.cancelled)
    finally:
        returned_at = time.time()
        try:
            _close_all(sinks.values())  # the writers' last copies
        finally:
            for k in sinks.values():
                k.store.close()  # durable at the end of the pose, whatever happened
    stored_at = [k.last_stored_at for k in sinks.values() if k.last_stored_at is not None]
    timing = {"capture_s": round(time.perf_counter() - t0, 4),
              "store_s": round(sum(k.store_s for k in sinks.values()), 4),
              # the last frame of every camera, not the controller's end
              "captured_at": max(stored_at) if stored_at else None,
              "controller_done_at": returned_at,  # after the integrity repeats and check
              "close_s": round(time.time() - returned_at, 4),
              **result.counters(),
              "trigger_late_s": round(result.trigger_late_s, 4)}
    ctx.check_cancelled()
    status = result.status
    if status not in ("complete", "flagged"):
        reason = result.reason or status
        raise RuntimeError(f"capture {status}: {reason}")
    for name, k in sinks.items():
        left = [i for i in range(total) if i not in k.have]
        if left:
            raise RuntimeError(f"capture ended with {len(left)} plan frames missing (first "
                               f"{left[0]}{f' of camera {name!r}' if several else ''})")
    out: dict[str, Any] = {"captured": len(missing), "resumed_from": have, **timing}
    per_camera = result.cameras if several else dict.fromkeys(dirs, result)
    for name, folder in dirs.items():  # durable before the pose is (the maps' commit fsyncs)
        cam = per_camera[name]
        if cam.status == "flagged":
            write_json_atomic(folder / VERDICT, {"flagged": cam.reason})
    verdict = _verdict(dirs, several)  # (frames of an earlier, flagged run stay flagged)
    if verdict:
        out["flagged"] = verdict
    return out


def _verdict(dirs: dict[str, Path], several: bool) -> str | None:
    """The stored integrity verdict of the cameras' frames (each flagged one named)."""
    found = {n: v for n, d in dirs.items() if (v := stored_verdict(d)) is not None}
    if not several:
        return next(iter(found.values()), None)
    return "; ".join(f"camera {n!r}: {v}" for n, v in found.items()) or None


def _close_all(sinks: Any) -> None:
    """Close every sink (their writers' last copies); raise the first error after all."""
    error: BaseException | None = None
    for k in sinks:
        try:
            k.close()
        except BaseException as exc:
            error = error or exc
    if error is not None:
        raise error


class LiveDecode(Protocol):
    """The streaming decode of one pose's frame store, running beside its capture."""

    def stop(self) -> None:
        """The capture failed: stop following the store (and wait for it to let go)."""

    def result(self) -> dict[str, Any]:
        """The decode's summary once every plan frame was folded in (raises its error)."""


class ThreadDecode:
    """`stream_decode_task` on a thread of this process (`phasecal capture`)."""

    def __init__(self, plan_path: Path, pose_dir: Path, out_path: Path,
                 **task_kwargs: Any) -> None:
        self.cancel = threading.Event()
        self.outcome: dict[str, Any] = {}
        self.thread = threading.Thread(
            target=self.run, args=(plan_path, pose_dir, out_path, task_kwargs),
            name="phasecal-decode")
        self.thread.start()

    def run(self, plan_path: Path, pose_dir: Path, out_path: Path,
            task_kwargs: dict[str, Any]) -> None:
        """The thread: the decode's summary or its error, kept for `result`."""
        try:
            self.outcome["result"] = stream_decode_task(
                TaskContext("decode", None, self.cancel), str(plan_path), str(pose_dir),
                str(out_path), **task_kwargs)
        except BaseException as exc:  # raised by `result`, on the caller's thread
            self.outcome["error"] = exc

    def stop(self) -> None:
        self.cancel.set()
        self.thread.join()

    def result(self) -> dict[str, Any]:
        self.thread.join()
        if "error" in self.outcome:
            raise self.outcome["error"]
        return self.outcome["result"]


class ThreadRigDecode(ThreadDecode):
    """`stream_decode_rig_task` on a thread of this process (`phasecal capture` on a rig of
    several cameras): `cameras` maps a name to (store folder, maps path, meta)."""

    def __init__(self, plan_path: Path, cameras: dict[str, tuple[Path, Path, dict[str, Any]]],
                 **task_kwargs: Any) -> None:
        self.cancel = threading.Event()
        self.outcome: dict[str, Any] = {}
        jobs = {name: (str(store), str(out), meta)
                for name, (store, out, meta) in cameras.items()}
        self.thread = threading.Thread(target=self.run_cameras,
                                       args=(plan_path, jobs, task_kwargs),
                                       name="phasecal-decode")
        self.thread.start()

    def run_cameras(self, plan_path: Path, jobs: dict[str, tuple[str, str, dict[str, Any]]],
                    task_kwargs: dict[str, Any]) -> None:
        """The thread: every camera's decode summary or the first error, kept for `result`."""
        try:
            self.outcome["result"] = stream_decode_rig_task(
                TaskContext("decode", None, self.cancel), str(plan_path), jobs, **task_kwargs)
        except BaseException as exc:  # raised by `result`, on the caller's thread
            self.outcome["error"] = exc


class ExecutorDecode:
    """`stream_decode_task` on the service's executor (a worker process), as part of the
    capture job `ctx`: the job's cancel reaches it and its progress is the job's."""

    def __init__(self, executor: Executor, ctx: TaskContext, plan_path: Path, pose_dir: Path,
                 out_path: Path, **task_kwargs: Any) -> None:
        self.executor, self.job_id = executor, ctx.job_id
        self.future = executor.run_task(stream_decode_task, str(plan_path), str(pose_dir),
                                        str(out_path), job_id=ctx.job_id,
                                        on_progress=ctx.progress, **task_kwargs)

    def stop(self) -> None:
        self.executor.cancel(self.job_id)  # the worker stops following the store

    def result(self) -> dict[str, Any]:
        return self.future.result()


def capture_live(ctx: TaskContext, rig: Rig, plan: Plan, pose_dir: Path, decode: LiveDecode,
                 on_frame: Any = None) -> dict[str, Any]:
    """Capture one camera's pose into its frame store while `decode` (started by the caller,
    before the first frame) follows the store; the capture's report. The decode is stopped
    when the capture fails; the maps come from `decode.result()`."""
    try:
        return capture_frames(ctx, rig, plan, pose_dir, on_frame=on_frame)
    except BaseException:
        decode.stop()
        raise


def capture_rig_live(ctx: TaskContext, rig: Rig, plan: Plan, dirs: dict[str, Path],
                     decode: LiveDecode, on_frame: Any = None) -> dict[str, Any]:
    """`capture_live` for several cameras: each camera's frames into its folder's store
    (`dirs`, see `camera_dirs`) while `decode` follows every store."""
    try:
        return capture_camera_frames(ctx, rig, plan, dirs, on_frame=on_frame)
    except BaseException:
        decode.stop()
        raise


class ExecutorRigDecode:
    """`stream_decode_rig_task` on the service's executor: one task of the capture job `ctx`
    decoding every camera's store (a thread per camera in one worker process: the decoder's
    kernels release the GIL), so no camera waits for a free worker."""

    def __init__(self, executor: Executor, ctx: TaskContext, plan_path: Path,
                 cameras: dict[str, tuple[Path, Path]], metas: dict[str, dict[str, Any]],
                 **task_kwargs: Any) -> None:
        self.executor, self.job_id = executor, ctx.job_id
        jobs = {name: (str(store), str(out), metas[name])
                for name, (store, out) in cameras.items()}
        self.future = executor.run_task(stream_decode_rig_task, str(plan_path), jobs,
                                        job_id=ctx.job_id, on_progress=ctx.progress,
                                        **task_kwargs)

    def stop(self) -> None:
        self.executor.cancel(self.job_id)  # the worker stops following the stores

    def result(self) -> dict[str, Any]:
        """Each camera's decode summary by name."""
        return self.future.result()
