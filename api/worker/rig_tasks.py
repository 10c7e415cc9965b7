"""The worker tasks of a rig: its calibration (every camera's maps of the chosen poses, fitted
jointly; writes rig.json (phasecal.rig/1) and result.json into the job's staging folder) and
its next-pose plan (every camera's own fit; run off the server that paces captures)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from calibration import (
    calibrate_rig_files,
    plan_rig_next_pose,
    save_rig,
    session_points,
    split_rig_options,
)
from calibration.shared.atomic import write_json_atomic
from calibration.shared.maps import load_maps
from calibration.shared.plan import read_plan
from calibration.shared.progress import TaskContext

RIG_OUTPUTS = ["rig.json", "result.json"]


def rig_calibrate_task(
    ctx: TaskContext, plan_path: str, entries: list[tuple[str, str, str, str]],
    models: dict[str, str], out_dir: str, *, options: dict[str, Any] | None = None,
    heldout_views: list[str] | None = None, reference: str | None = None,
) -> dict[str, Any]:
    """Fit the rig to (camera, view, "maps", path) entries; the summary the job stores."""
    rig_opts, model_opts = split_rig_options(options)
    result = calibrate_rig_files(
        plan_path, entries, models, reference=reference, options=rig_opts,
        model_options={c: model_opts for c in models}, heldout_views=heldout_views,
        progress=ctx.progress, cancelled=ctx.cancelled)
    ctx.check_cancelled()
    out = Path(out_dir)
    save_rig(result.rig, out / "rig.json")
    stats = result.json_stats()
    write_json_atomic(out / "result.json", {"stats": stats})
    summary = {k: stats[k] for k in ("reference", "models", "reduced_chi2", "extrinsics",
                                     "intrinsics_fixed", "n_points", "outliers_dropped",
                                     "converged") if k in stats}
    if "heldout" in stats:
        summary["heldout"] = stats["heldout"]
    return {"stats": summary, "exports": list(RIG_OUTPUTS)}


def rig_guidance_task(plan_path: str, maps: dict[str, dict[str, str]], reference: str,
                      model: str, out_dir: str, header: dict[str, Any],
                      min_visible: float = 1.0) -> None:
    """Plan a rig's next pose from every camera's maps (camera -> pose -> path) and write
    next-pose.json (`header` plus the suggestion) into `out_dir`; ValueError when the poses
    do not support it."""
    screen = read_plan(plan_path).screen
    points, sizes = {}, {}
    for cam, views in maps.items():
        decoded = [load_maps(p) for p in views.values()]
        points[cam] = dict(zip(views, session_points(decoded, screen), strict=True))
        h, w = decoded[0].shape
        sizes[cam] = (w, h)
    sug = plan_rig_next_pose(points, sizes, screen, reference, model, min_visible)
    write_json_atomic(Path(out_dir) / "next-pose.json", {**header, **sug.to_json()})
