"""Calibrate the OpenCV-family models (opencv5, opencv-rational, fisheye) from decoded maps:
validate the inputs, fit (OpenCV init, then the weighted fit on every pixel,
`calibration.metrology.refine`), evaluate training and held-out poses."""

from __future__ import annotations

import time

import numpy as np

from calibration.evaluate import attach_residuals, heldout_errors, summarize
from calibration.fit.classic.options import MIN_POSES, ParametricOptions
from calibration.fit.correspondences import point_set, subsample
from calibration.fit.result import CalibrationResult
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import ScreenGeometry
from calibration.shared.progress import CancelCheck, Cancelled, ProgressFn

MIN_VALID_PIXELS = 100


def _check_inputs(maps: list[DecodedMaps], heldout: list[int]) -> tuple[int, int]:
    """Common checks: same image size, enough valid pixels, held-out indices; returns (W, H)."""
    if not maps:
        raise ValueError("maps: no poses given")
    shapes = {m.shape for m in maps}
    if len(shapes) != 1:
        listing = ", ".join(f"pose {i}: {m.shape[1]}x{m.shape[0]}" for i, m in enumerate(maps))
        raise ValueError(f"maps: image sizes differ ({listing})")
    for i, m in enumerate(maps):
        if m.valid_count() < MIN_VALID_PIXELS:
            raise ValueError(f"maps: pose {i} has {m.valid_count()} valid pixels "
                             f"(need >= {MIN_VALID_PIXELS})")
    bad = [h for h in heldout if not 0 <= h < len(maps)]
    if bad or len(set(heldout)) != len(heldout):
        raise ValueError(f"heldout: expected distinct pose indices in [0, {len(maps) - 1}], "
                         f"got {heldout}")
    h, w = maps[0].shape
    return w, h


def calibrate_parametric(
    maps: list[DecodedMaps], screen: ScreenGeometry, model: str, *,
    options: ParametricOptions, heldout: list[int] | None = None,
    progress: ProgressFn | None = None, cancelled: CancelCheck | None = None,
) -> CalibrationResult:
    """Fit OpenCV-family `model` to the poses not in `heldout`; training and held-out stats."""
    held = list(heldout or [])
    size = _check_inputs(maps, held)
    train = [i for i in range(len(maps)) if i not in held]
    if len(train) < MIN_POSES:
        raise ValueError(f"{model}: needs >= {MIN_POSES} training poses, got {len(train)} "
                         f"({len(maps)} given, {len(held)} held out)")
    t0 = time.perf_counter()
    pts = [point_set(m, screen) for m in maps]

    def report(i: int, n: int, msg: str) -> None:
        if cancelled is not None and cancelled():
            raise Cancelled(f"{model}: calibration cancelled")
        if progress is not None:
            progress(i, n + 1, msg)

    from calibration.metrology.refine import fit_parametric_dense, heldout_points

    fitted, poses, used, stats, dense = fit_parametric_dense(
        [pts[i] for i in train], size, model, screen, options, report)
    result = CalibrationResult(model=fitted, poses=poses)
    report(1, 1, f"{model}: evaluating")
    per_pose = attach_residuals(result, used, train)
    stats.update(summarize(per_pose))
    stats["per_pose"] = per_pose
    stats["training_poses"] = train
    if held:
        rng = np.random.default_rng(options.seed)
        held_pts = [subsample(pts[i], options.max_points_per_pose) for i in held]
        if dense is not None:  # moved to where a flat bare screen shows them
            held_pts = heldout_points(dense, held_pts, rng)
        stats["heldout"] = heldout_errors(fitted, held_pts, held, rng)
    stats["wall_s"] = time.perf_counter() - t0
    result.stats = stats
    fitted.stats = {k: stats[k] for k in ("rms_px", "expected_rms_px", "noise_floor_ratio",
                                          "model_adequate", "param_std", "per_pose",
                                          "screen", "reduced_chi2")}
    if held:
        fitted.stats["heldout"] = stats["heldout"]
    if "fit_note" in stats:  # a rational fit moved away from 0/0 (metrology.refine)
        fitted.stats["fit_note"] = stats["fit_note"]
    return result
