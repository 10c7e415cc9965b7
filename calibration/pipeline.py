"""The two steps every front end runs, written once: decode a pose's frames to maps, and
calibrate maps into a model folder (model.json, result.json, exports). The worker tasks
(REST jobs, batches) and the CLI call these; they add only their own I/O around them."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from calibration.decode import DecodeError, DecodeOptions, decode_stack, read_frames
from calibration.models.base import ModelError, jsonable, save_model
from calibration.shared.atomic import atomic_path, write_json_atomic
from calibration.shared.maps import DecodedMaps, load_maps
from calibration.shared.observations import load_observations
from calibration.shared.plan import Plan, read_plan
from calibration.shared.progress import CancelCheck, ProgressFn, check_cancelled

if TYPE_CHECKING:  # the fit stack (pydantic, scipy) stays out of `phasecal decode`'s imports
    from calibration.fit.result import CalibrationResult


def decode_frames(
    plan: Plan, frames_path: str | Path, *, noise: Any = None,
    saturation_dn: float | None = None, options: DecodeOptions | None = None,
    meta: dict[str, Any] | None = None, progress: ProgressFn | None = None,
    cancelled: CancelCheck | None = None, prepare: bool = False,
    into: dict[str, Any] | None = None,
) -> DecodedMaps:
    """Decode a `.npy` stack or folder of frame images (plan order) to maps.

    `noise`: per-frame camera noise sigma in DN, a noise model, or None to estimate it;
    `prepare`: load the compiled finish kernel first (worth it in long-lived workers);
    `into`: the arrays to decode into (`calibration.shared.maps_file.MapsFile.outputs`)."""
    source = read_frames(frames_path)
    if source.count != len(plan.frames):
        raise DecodeError(f"{frames_path}: {source.count} frames, but the plan has "
                          f"{len(plan.frames)} (frame i must show plan frame i)")
    return decode_stack(plan, source, noise=noise, saturation_dn=saturation_dn,
                        options=options, meta=meta, progress=progress, cancelled=cancelled,
                        prepare=prepare, into=into)


def calibrate_files(
    plan_path: str | Path, maps_paths: list[str], model: str, *,
    options: dict[str, Any] | None = None, heldout: list[int] | None = None,
    progress: ProgressFn | None = None, cancelled: CancelCheck | None = None,
) -> CalibrationResult:
    """Fit `model` to maps files of several poses; poses `heldout` (indices into
    `maps_paths`) are left out of the fit and validated."""
    from calibration.fit.dispatch import calibrate

    plan = read_plan(plan_path)
    maps = []
    for i, p in enumerate(maps_paths):
        check_cancelled(cancelled, "calibration")
        maps.append(load_maps(p))
        if progress is not None:
            progress(i + 1, len(maps_paths), "load")
    return calibrate(maps, plan.screen, model, options=options, heldout=heldout,
                     progress=progress, cancelled=cancelled)


def calibrate_observation_files(
    paths: list[str], model: str, *, options: dict[str, Any] | None = None,
    cross_validate: int = 0, progress: ProgressFn | None = None,
    cancelled: CancelCheck | None = None,
) -> CalibrationResult:
    """Fit `model` to target observation files (`phasecal.observations/1`), each its own view
    of one camera; `cross_validate` >= 2 also fits that many disjoint view sets and compares
    them."""
    from calibration.fit.sparse.calibrate import calibrate_observations

    views = []
    for i, p in enumerate(paths):
        check_cancelled(cancelled, "calibration")
        views.append(load_observations(p))
        if progress is not None:
            progress(i + 1, len(paths), "load")
    return calibrate_observations(views, model, options=options,
                                  cross_validate_folds=cross_validate, progress=progress,
                                  cancelled=cancelled)


def write_model_folder(
    result: CalibrationResult, model: str, out_dir: str | Path
) -> dict[str, Any]:
    """model.json, result.json (stats, poses) and every export the model has, each written
    atomically into `out_dir`; returns {"stats", "exports"} (the exports' file names)."""
    out = Path(out_dir)
    save_model(result.model, out / "model.json")
    poses = [{"rotation": p.rotation.tolist(), "translation_mm": p.translation.tolist(),
              "rms_px": p.rms_px, "rms_screen_px": p.rms_screen_px, "n_points": p.n_points}
             for p in result.poses]
    stats = jsonable(dict(result.stats))
    write_json_atomic(out / "result.json", {"model": model, "stats": stats, "poses": poses})
    return {"stats": stats, "exports": _write_exports(result, out)}


def _write_exports(result: CalibrationResult, out: Path) -> list[str]:
    """OpenCV YAML and ROS camera_info (pinhole-family models) and the residual plot."""
    from calibration import export, report

    written: list[str] = []
    jobs = (
        ("opencv.yaml", export.export_opencv_yaml),
        ("camera_info.yaml", export.export_ros_yaml),
        ("residuals.png", report.write_residual_report),
    )
    for name, fn in jobs:
        try:
            with atomic_path(out / name) as tmp:  # same extension: writers pick the format
                fn(result if name == "residuals.png" else result.model, tmp)
        except ModelError:
            continue  # this model has no such form (e.g. generic models and OpenCV YAML)
        written.append(name)
    return written

