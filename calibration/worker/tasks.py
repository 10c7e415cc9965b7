"""Module-level task functions run by an executor; data moves by reference (file paths).

Each task takes a `TaskContext` first, reads its inputs from paths, writes its outputs
atomically to the given paths and returns a small JSON-able summary.
"""

from __future__ import annotations

import time
from typing import Any

from calibration.progress import Cancelled, TaskContext


def decode_task(
    ctx: TaskContext,
    plan_path: str,
    frames_path: str,
    out_path: str,
    *,
    noise: Any = None,
    meta: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Decode captured frames (`.npy` stack or image folder) to a maps NPZ at `out_path`.

    `noise` is the camera's per-frame noise: sigma in DN, a sensor noise model (anything
    with `noise_sigma_dn(mean)`), or None to estimate it from the fit residuals.
    """
    from calibration.maps import save_maps
    from calibration.pipeline import decode_frames
    from calibration.plan import read_plan

    t0 = time.perf_counter()
    maps = decode_frames(read_plan(plan_path), frames_path, noise=noise, meta=meta,
                         progress=ctx.progress, cancelled=ctx.cancelled)
    save_maps(maps, out_path)
    h, w = maps.shape
    return {
        "valid_pixels": maps.valid_count(),
        "width": w,
        "height": h,
        "wall_s": round(time.perf_counter() - t0, 3),
    }


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
    from calibration.pipeline import calibrate_files, write_model_folder

    held = list(heldout_paths or [])
    result = calibrate_files(plan_path, [*maps_paths, *held], model, options=options,
                             heldout=list(range(len(maps_paths), len(maps_paths) + len(held))),
                             progress=ctx.progress, cancelled=ctx.cancelled)
    ctx.check_cancelled()
    ctx.progress(0, 1, "write")
    summary = write_model_folder(result, model, out_dir)
    ctx.progress(1, 1, "write")
    return summary


__all__ = ["Cancelled", "calibrate_task", "decode_task"]
