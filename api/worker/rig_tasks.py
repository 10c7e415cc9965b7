"""The worker tasks of a rig: its calibration (every camera's maps of the chosen poses, fitted
jointly; writes rig.json (phasecal.rig/1) and result.json into the job's staging folder) and
its next-pose plan (every camera's own fit and a picture per camera; run off the server that
paces captures)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from calibration import (
    RigSuggestion,
    calibrate_rig_files,
    plan_rig_next_pose,
    rig_camera_guidance_png,
    rig_sigma_range,
    save_rig,
    session_points,
    split_rig_options,
)
from calibration.shared.atomic import write_json_atomic
from calibration.shared.maps import load_maps
from calibration.shared.plan import read_plan
from calibration.shared.progress import TaskContext

RIG_OUTPUTS = ["rig.json", "result.json"]
RIG_PICTURE = "next-pose-{camera}.png"  # one per camera, next to the plan's next-pose.json


def rig_calibrate_task(
    ctx: TaskContext, plan_path: str | None, entries: list[tuple[str, str, str, str]],
    models: dict[str, str], out_dir: str, *, options: dict[str, Any] | None = None,
    heldout_views: list[str] | None = None, reference: str | None = None,
) -> dict[str, Any]:
    """Fit the rig to (camera, view, "maps" | "observations", path) entries (the plan only
    for maps); the summary the job stores."""
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
                                     "intrinsics_fixed", "intrinsics_rays_in_covariance",
                                     "n_points", "outliers_dropped", "converged")
               if k in stats}
    if "heldout" in stats:
        summary["heldout"] = stats["heldout"]
    return {"stats": summary, "exports": list(RIG_OUTPUTS)}


def plan_rig_files(plan_path: str, maps: dict[str, dict[str, str]], reference: str,
                   model: str, min_visible: float = 1.0) -> RigSuggestion:
    """A rig's next pose from every camera's maps (camera -> view -> path; views named alike
    are one screen pose); ValueError when the poses do not support it."""
    screen = read_plan(plan_path).screen
    points, sizes = {}, {}
    for cam, views in maps.items():
        decoded = [load_maps(p) for p in views.values()]
        points[cam] = dict(zip(views, session_points(decoded, screen), strict=True))
        h, w = decoded[0].shape
        sizes[cam] = (w, h)
    return plan_rig_next_pose(points, sizes, screen, reference, model, min_visible)


def write_rig_pictures(sug: RigSuggestion, model: str, out_dir: Path) -> dict[str, Path]:
    """A picture per camera (`RIG_PICTURE`: its ray sigma now, on the rig's one colour range,
    with the suggested screen where it sees it) in `out_dir`; camera -> path."""
    span = rig_sigma_range(list(sug.maps_before.values()))
    written = {}
    for cam in sug.per_camera:
        name = cam["camera"]
        sigma = cam["predicted_worst_ray_sigma_urad"]
        seen = sug.placements.get(name)
        detail = (f"worst {sigma['now']:.3g} urad, {sigma['after']:.3g} after"
                  if seen is not None else f"worst {sigma['now']:.3g} urad")
        written[name] = out_dir / RIG_PICTURE.format(camera=name)
        rig_camera_guidance_png(
            sug.maps_before[name], None if seen is None else seen.border_px,
            sug.image_sizes[name], span, f"camera {name} ({model}): "
            + ("serves the suggested pose" if seen is not None else "does not see it"),
            detail, written[name])
    return written


def rig_guidance_task(plan_path: str, maps: dict[str, dict[str, str]], reference: str,
                      model: str, out_dir: str, header: dict[str, Any],
                      min_visible: float = 1.0) -> None:
    """Plan a rig's next pose from every camera's maps (camera -> pose -> path) and write
    next-pose.json (`header` plus the suggestion) and a picture per camera into `out_dir`;
    ValueError when the poses do not support it."""
    sug = plan_rig_files(plan_path, maps, reference, model, min_visible)
    write_rig_pictures(sug, model, Path(out_dir))
    write_json_atomic(Path(out_dir) / "next-pose.json", {**header, **sug.to_json()})
