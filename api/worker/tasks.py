"""Module-level task functions run by an executor; data moves by reference (file paths).

Each task takes a `TaskContext` first, reads its inputs from paths, writes its outputs
atomically to the given paths and returns a small JSON-able summary.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from calibration import (
    COMPILED_MIN_PIXELS,
    DecodeOptions,
    StreamingDecoder,
    calibrate_files,
    decode_frames,
    holds_pixels,
    retain_freed_memory,
    warm_heap,
    warm_up,
    write_model_folder,
)
from calibration.shared.frame_store import FrameStore
from calibration.shared.maps import save_maps
from calibration.shared.maps_file import MapsFile, prefaulted, warm_resident
from calibration.shared.plan import read_plan
from calibration.shared.progress import Cancelled, TaskContext


def _decoder_setup(options: dict[str, Any] | None) -> tuple[Any, Any]:
    """(DecodeOptions, saturation_dn) from a JSON-able options dict (None: defaults)."""
    opts = dict(options or {})
    saturation = opts.pop("saturation_dn", None)
    try:
        return DecodeOptions(**opts), saturation
    except TypeError as exc:
        raise ValueError(f"decode options: {exc}") from None


def _summary(maps: Any, t0: float) -> dict[str, Any]:
    h, w = maps.shape
    return {"valid_pixels": maps.valid_count(), "width": w, "height": h,
            "wall_s": round(time.perf_counter() - t0, 3)}


DROP_DELAY_S = 0.25  # how long after a live decode returns its maps are unmapped


def _drop_later(obj: Any) -> None:
    """Drop `obj` in a daemon thread `DROP_DELAY_S` from now, once the caller (which drops its
    own references) has returned: a 5 MP pose's maps are views of a 205 MB file mapping whose
    unmapping takes ~0.03 s, which the pose's ready time need not include."""
    box, delay_s = [obj], DROP_DELAY_S
    del obj

    def drop() -> None:
        time.sleep(delay_s)
        box.clear()

    threading.Thread(target=drop, name="drop-maps", daemon=True).start()


def _keep_heap(pixels: int, decodes: int = 1) -> None:
    """A worker keeps the heap memory its decodes free (`calibration.decode.heap`): no
    first-touch page faults of the finish's temporaries after the last frame; for images
    the compiled kernels decode, also faulted in now (once per worker, for `decodes` at
    once: a rig's cameras)."""
    retain_freed_memory(decodes)
    if pixels >= COMPILED_MIN_PIXELS:
        warm_heap(decodes)


def decode_task(
    ctx: TaskContext,
    plan_path: str,
    frames_path: str,
    out_path: str,
    *,
    noise: Any = None,
    meta: dict[str, Any] | None = None,
    options: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Decode captured frames (`.npy` stack or image folder) to a maps NPZ at `out_path`.

    `noise` is the camera's per-frame noise: sigma in DN, a sensor noise model (anything
    with `noise_sigma_dn(mean)`), or None to estimate it from the fit residuals.
    `options`: `DecodeOptions` fields and `saturation_dn`.
    """
    t0 = time.perf_counter()
    opts, saturation = _decoder_setup(options)
    maps = decode_frames(read_plan(plan_path), frames_path, noise=noise, saturation_dn=saturation,
                         options=opts, meta=meta, progress=ctx.progress, cancelled=ctx.cancelled,
                         prepare=True)  # long-lived workers: load the compiled kernel once
    save_maps(maps, out_path)
    return _summary(maps, t0)


def stream_decode_task(
    ctx: TaskContext,
    plan_path: str,
    store_dir: str,
    out_path: str,
    *,
    noise: Any = None,
    meta: dict[str, Any] | None = None,
    options: dict[str, Any] | None = None,
    poll_s: float = 0.002,
    durable: bool = True,
    compiled: bool = False,
    resident_maps: bool = False,
    decodes: int = 1,
) -> dict[str, Any]:
    """Decode a pose while it is captured: follow its `FrameStore` and fold in each frame
    as soon as it is stored (frames stored before the task started, e.g. by an interrupted
    capture, come first). Ends with the maps once every plan frame is in; the capture side
    cancels the job if it fails. Reports progress only for the final stage. The frames are
    read from the capture side's shared memory where it staged them (`FrameStore.sources`).
    The maps file is laid out before the first frame and the decoder writes into it
    (`MapsFile`); its pages are faulted in at idle priority while frames arrive. With
    `resident_maps` (a rig's cameras) it is laid out in a buffer this worker keeps from pose
    to pose instead, and the commit writes it to disk with O_DIRECT: one camera's 205 MB of
    page cache (5 MP) is faulted in during the capture's idle time and leaves nothing to
    write after the last frame (ready 0.27 s after it, against 0.33 with the O_DIRECT
    write), four cameras' 820 MB is not (seconds of faults after the last frame on a VM).
    `durable=False` writes the maps without fsync (the caller makes them durable after the
    pose is ready). `compiled`: the compiled
    kernels at every image size (a long-lived worker loads them once: a 640x480 pose's finish
    ~3x faster; a one-off process would load them during the capture). Timings (wall, and CPU
    seconds of this process: all its threads) and the share of the maps file's pages faulted
    in ahead by the last frame (`prefaulted`) in the summary. `decodes`: how many decodes
    this worker runs at once (a rig's cameras), whose freed heap it keeps (`_keep_heap`)."""
    plan = read_plan(plan_path)
    opts, saturation = _decoder_setup(options)
    total = len(plan.frames)
    store = FrameStore(store_dir, total)
    store.wait_open(ctx.cancelled)
    ctx.check_cancelled()
    added = np.zeros(total, dtype=bool)
    looks = 0
    # the maps file, laid out now: its pages (or a new resident buffer's) are faulted in at
    # idle priority while frames arrive (first-touch page faults: ~0.5 CPU s at 5 MP on a VM)
    out = MapsFile(out_path, store.shape, plan.axes(), resident=resident_maps)
    with prefaulted(out) as ahead:
        decoder = StreamingDecoder(plan, store.shape, noise=noise, saturation_dn=saturation,
                                   options=opts, compiled=compiled)
        decoder.prepare()
        _keep_heap(store.shape[0] * store.shape[1], decodes)
        try:
            while not added.all():
                if looks % 16 == 0:  # (a worker process's cancel flag: a round trip)
                    ctx.check_cancelled()
                looks += 1
                new = np.setdiff1d(store.stored(), np.flatnonzero(added), assume_unique=True)
                # stored frames of complete period groups, one cache-blocked pass per look,
                # from the capture side's shared memory where it staged them
                ready = decoder.ready_frames(new.tolist())
                if not ready:
                    time.sleep(poll_s)
                    continue
                for part, stack in store.sources(ready):
                    decoder.add_frames(part, stack, rows=part)
                store.verify()
                added[ready] = True
        finally:
            store.reader_done()
        caught_up_at = time.time()  # wall clock: the capture side reports its last frame's
        t0 = time.perf_counter()  # the time after the last frame: what the pose waits for
        ahead.stop()  # the decoder faults in what is left, if anything
        share_prefaulted = ahead.done / ahead.total
        ctx.progress(total, total, "unwrap")
        c0 = time.process_time()
        maps = decoder.finish(dict(meta or {}), into=out.outputs(), final_rows=out.write_rows)
        decoder.release()  # its sums, zeroed again, serve this worker's next pose
        t1, c1 = time.perf_counter(), time.process_time()
        out.commit(maps, durable=durable)  # durable=False: page cache, fsync by the caller
    summary = {**_summary(maps, t0), "caught_up_at": caught_up_at,
               "finish_s": round(t1 - t0, 3), "finish_cpu_s": round(c1 - c0, 3),
               "write_s": round(time.perf_counter() - t1, 3),
               "write_cpu_s": round(time.process_time() - c1, 3),
               "prefaulted": round(share_prefaulted, 3)}
    if resident_maps:
        del maps
        out.recycle()  # the buffer holds this worker's next pose's maps
    else:
        _drop_later(maps)  # (unmapped after the summary is on its way)
        del maps
    return summary


class CameraDecodeContext(TaskContext):
    """One camera's decode inside a several-camera task: it stops when the job is cancelled
    or another camera's decode failed (`stop`), and reports its progress through the job's."""

    def __init__(self, job: TaskContext, stop: threading.Event) -> None:
        super().__init__(job.job_id, job.progress, stop)
        self.job = job

    def cancelled(self) -> bool:
        return self.job.cancelled() or super().cancelled()


def stream_decode_rig_task(
    ctx: TaskContext,
    plan_path: str,
    cameras: dict[str, tuple[str, str, dict[str, Any]]],
    **task_kwargs: Any,
) -> dict[str, dict[str, Any]]:
    """`stream_decode_task` for every camera of a several-camera pose at once: `cameras`
    maps a name to (store folder, maps path, meta). One thread per camera in this worker
    (the decoder's kernels release the GIL, so the cameras' decodes share the cores), so a
    pose of more cameras than the pool has workers still decodes every camera while it is
    captured; each camera's maps are laid out in a buffer the worker keeps (`resident_maps`).
    The first failure stops the other cameras' decodes and is raised; the summaries by
    camera name otherwise."""
    stop = threading.Event()

    def one(name: str) -> dict[str, Any]:
        store_dir, out_path, meta = cameras[name]
        try:
            return stream_decode_task(CameraDecodeContext(ctx, stop), plan_path, store_dir,
                                      out_path, meta=meta, resident_maps=True,
                                      decodes=len(cameras), **task_kwargs)
        except BaseException:
            stop.set()
            raise

    with ThreadPoolExecutor(max_workers=len(cameras), thread_name_prefix="camera-decode") as pool:
        futures = {name: pool.submit(one, name) for name in cameras}
        outcomes: dict[str, dict[str, Any]] = {}
        errors: list[BaseException] = []
        for name, fut in futures.items():
            try:
                outcomes[name] = fut.result()
            except BaseException as exc:
                errors.append(exc)
    if errors:  # the failure itself, not the cancels it caused
        raise next((e for e in errors if not isinstance(e, Cancelled)), errors[0])
    return outcomes


def warm_decode_task(pixels: int, plan_path: str | None = None,
                     shape: tuple[int, int] | None = None, noise: Any = None,
                     sets: int = 1, resident_maps: bool = False) -> None:
    """Load the decoder's compiled kernels in this worker (~1.4 CPU s once per process; live
    decodes use them at every image size): a live capture submits this next to its decode
    task, so the worker that decodes a later pose does not load them while that pose's
    frames arrive (under load, late enough to delay the pose). With `plan_path` and `shape`
    (and the capture's `noise`) it also allocates `sets` decodes' sums (a rig's cameras of
    that size decode at once), with `resident_maps` their maps buffers too, and keeps them
    (`sums_cache`, `resident_buffers`) unless this worker already keeps as many of images
    this size (another camera's, e.g. a preview camera's small ones, are replaced): ~1 GB a
    camera at 5 MP, ~2.3 CPU s of first-touch page faults or far more on a VM whose host
    reclaimed the memory, paid once per worker while a capture runs rather than by the
    worker's first pose after its last frame. At normal CPU priority: a task at idle
    priority is starved by any busy process, and the decode tasks queued behind it with it
    (seen: poses ready 20-75 s late under load)."""
    warm_up()
    if (plan_path is not None and shape is not None
            and not holds_pixels(int(shape[0]) * int(shape[1]), sets)):
        plan = read_plan(plan_path)
        if resident_maps:
            warm_resident(tuple(shape), plan.axes(), sets)
        decoders = [StreamingDecoder(plan, tuple(shape), noise=noise, compiled=True)
                    for _ in range(sets)]
        for decoder in decoders:
            decoder.prepare()
        for decoder in decoders:
            decoder.release()
    # after the kept sums (their members under glibc's mmap threshold come from the heap):
    # the free heap faulted in now lies above them, where the finishes' temporaries go
    _keep_heap(pixels, sets)


def calibrate_task(
    ctx: TaskContext,
    plan_path: str,
    maps_paths: list[str],
    model: str,
    out_dir: str,
    *,
    options: dict[str, Any] | None = None,
    heldout_paths: list[str] | None = None,
) -> dict[str, Any]:
    """Fit `model` to the maps of several poses; write model.json, result.json and exports."""
    held = list(heldout_paths or [])
    result = calibrate_files(plan_path, [*maps_paths, *held], model, options=options,
                             heldout=list(range(len(maps_paths), len(maps_paths) + len(held))),
                             progress=ctx.progress, cancelled=ctx.cancelled)
    ctx.check_cancelled()
    ctx.progress(0, 1, "write")
    summary = write_model_folder(result, model, out_dir)
    ctx.progress(1, 1, "write")
    return summary


__all__ = ["Cancelled", "calibrate_task", "decode_task", "stream_decode_rig_task",
           "stream_decode_task", "warm_decode_task"]
