"""Module-level task functions run by an executor; data moves by reference (file paths).

Each task takes a `TaskContext` first, reads its inputs from paths, writes its outputs
atomically to the given paths and returns a small JSON-able summary.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from calibration.progress import Cancelled, TaskContext


def write_json_atomic(path: str | Path, data: Any) -> None:
    """Write JSON through a temp file in the same folder, then rename."""
    p = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=p.name + ".", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(data, fh, indent=1, allow_nan=False)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _decoder_setup(options: dict[str, Any] | None) -> tuple[Any, Any]:
    """(DecodeOptions, saturation_dn) from a JSON-able options dict (None: defaults)."""
    from calibration.decode import DecodeOptions

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
    from calibration.decode import DecodeError, StreamingDecoder, read_frames
    from calibration.maps import save_maps
    from calibration.plan import read_plan

    t0 = time.perf_counter()
    plan = read_plan(plan_path)
    opts, saturation = _decoder_setup(options)
    source = read_frames(frames_path)
    total = len(plan.frames)
    if source.count != total:
        raise DecodeError(f"{frames_path}: {source.count} frames but the plan has {total}")
    decoder = StreamingDecoder(plan, source.shape, noise=noise, saturation_dn=saturation,
                               options=opts)
    for index, image in enumerate(source):
        ctx.check_cancelled()
        decoder.add(index, image)
        ctx.progress(index + 1, total, "decode")
    ctx.progress(total, total, "unwrap")
    maps = decoder.finish(dict(meta or {}))
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
) -> dict[str, Any]:
    """Decode a pose while it is captured: follow its `FrameStore` and fold in each frame
    as soon as it is stored (frames stored before the task started, e.g. by an interrupted
    capture, come first). Ends with the maps once every plan frame is in; the capture side
    cancels the job if it fails. Reports progress only for the final stage."""
    from calibration.decode import StreamingDecoder
    from calibration.decode.frame_store import FrameStore
    from calibration.maps import save_maps
    from calibration.plan import read_plan

    plan = read_plan(plan_path)
    opts, saturation = _decoder_setup(options)
    total = len(plan.frames)
    store = FrameStore(store_dir, total)
    store.wait_open(ctx.cancelled)
    ctx.check_cancelled()
    decoder = StreamingDecoder(plan, store.shape, noise=noise, saturation_dn=saturation,
                               options=opts)
    added = np.zeros(total, dtype=bool)
    while not added.all():
        ctx.check_cancelled()
        new = np.setdiff1d(store.stored(), np.flatnonzero(added), assume_unique=True)
        if new.size == 0:
            time.sleep(poll_s)
            continue
        for index in new.tolist():
            decoder.add(index, store.frame(index))
            added[index] = True
    t0 = time.perf_counter()  # the time after the last frame: what the pose waits for
    ctx.progress(total, total, "unwrap")
    maps = decoder.finish(dict(meta or {}))
    save_maps(maps, out_path)
    return _summary(maps, t0)


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
    from calibration.fit.dispatch import calibrate
    from calibration.maps import load_maps
    from calibration.models.base import _jsonable, save_model
    from calibration.plan import read_plan

    t0 = time.perf_counter()
    out = Path(out_dir)
    plan = read_plan(plan_path)
    ctx.progress(0, len(maps_paths), "load")
    maps_list = []
    for i, p in enumerate(maps_paths):
        ctx.check_cancelled()
        maps_list.append(load_maps(p))
        ctx.progress(i + 1, len(maps_paths), "load")
    heldout = list(range(len(maps_list), len(maps_list) + len(heldout_paths or [])))
    maps_list += [load_maps(p) for p in heldout_paths or []]
    result = calibrate(
        maps_list,
        plan.screen,
        model,
        options=options or {},
        heldout=heldout,
        progress=ctx.progress,
        cancelled=ctx.cancelled,
    )
    ctx.check_cancelled()
    ctx.progress(0, 1, "write")
    save_model(result.model, out / "model.json")
    poses = [
        {
            "rotation": p.rotation.tolist(),
            "translation_mm": p.translation.tolist(),
            "rms_px": p.rms_px,
            "rms_screen_px": p.rms_screen_px,
            "n_points": p.n_points,
        }
        for p in result.poses
    ]
    stats = _jsonable(dict(result.stats))
    stats.setdefault("wall_s", round(time.perf_counter() - t0, 3))
    write_json_atomic(out / "result.json", {"model": model, "stats": stats, "poses": poses})
    exports = _write_exports(result, out)
    ctx.progress(1, 1, "write")
    return {"stats": stats, "exports": exports}


def _write_exports(result: Any, out: Path) -> list[str]:
    """OpenCV YAML and ROS camera_info (pinhole-family models) and the residual plot.

    Each file is written under a temporary name with the same extension (the writers
    pick the format from it) and renamed into place.
    """
    from calibration import export, report
    from calibration.models.base import ModelError

    written: list[str] = []
    jobs = (
        ("opencv.yaml", export.export_opencv_yaml),
        ("camera_info.yaml", export.export_ros_yaml),
        ("residuals.png", report.write_residual_report),
    )
    for name, fn in jobs:
        tmp = out / f"tmp-{name}"
        try:
            fn(result if name == "residuals.png" else result.model, tmp)
        except ModelError:
            tmp.unlink(missing_ok=True)
            continue  # this model has no such form (e.g. generic models and OpenCV YAML)
        os.replace(tmp, out / name)
        written.append(name)
    return written


__all__ = ["Cancelled", "calibrate_task", "decode_task", "write_json_atomic"]
