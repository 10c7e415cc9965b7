"""The entry point of a calibration from target observations: check the model and options,
fit in pixel space, add the projection-uncertainty map and, if asked, cross-validation."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from calibration.fit.registry import model_spec
from calibration.fit.result import CalibrationResult
from calibration.fit.sparse.crossval import cross_validate
from calibration.fit.sparse.fit import to_result
from calibration.fit.sparse.options import ObservationOptions
from calibration.fit.sparse.sgcc import fit_sparse
from calibration.fit.sparse.target_shape import TargetShape
from calibration.fit.sparse.uncertainty import projection_sigma_map
from calibration.shared.observations import TargetObservations
from calibration.shared.progress import CancelCheck, ProgressFn, check_cancelled

#: Models that cannot be fitted to sparse points, and why.
REFUSED: dict[str, str] = {
    "raygrid": "raygrid interpolates one ray per pixel from dense decoded maps; a few hundred "
               "target points cannot fill its grid (use a parametric model: opencv5, "
               "opencv-rational, fisheye; or sgcc, sgcc-noncentral)",
}


def observation_refusal(model: str) -> str | None:
    """Why `model` cannot be fitted to target observations, or None if it can."""
    return REFUSED.get(model)


def parse_observation_options(model: str,
                              options: dict[str, Any] | ObservationOptions | None
                              ) -> ObservationOptions:
    """Typed options of an observation fit (typed ones pass through); ValueError naming the
    model it refuses or the bad field, as the registry reports them for maps."""
    spec = model_spec(model)
    if model in REFUSED:
        raise ValueError(f"model: {model} cannot be fitted to target observations: "
                         f"{REFUSED[model]}")
    return dataclasses.replace(spec, options=ObservationOptions).parse_options(options)


def calibrate_observations(
    observations: list[TargetObservations], model: str, *,
    options: dict[str, Any] | ObservationOptions | None = None, cross_validate_folds: int = 0,
    progress: ProgressFn | None = None, cancelled: CancelCheck | None = None,
) -> CalibrationResult:
    """Fit `model` to the views (each file one view of one camera); stats as every fit's,
    plus the target shape, outliers per view, projection sigma and cross-validation."""
    opts = parse_observation_options(model, options)
    steps = 2 + (1 if cross_validate_folds else 0)

    def report(done: int, total: int, stage: str) -> None:
        check_cancelled(cancelled, "calibration")
        if progress is not None:
            progress(min(done, total), total, stage)

    fit = fit_sparse(observations, model, opts, lambda i, n, s: report(0, steps, s))
    report(1, steps, f"{model}: projection uncertainty")
    fit.stats["projection_sigma_px"] = projection_sigma_map(fit.model, fit.intrinsics_covariance)
    if cross_validate_folds:
        report(2, steps, f"{model}: cross-validation")
        fit.stats["cross_validation"] = cross_validate(observations, model, opts,
                                                       cross_validate_folds)
    result = to_result(fit)
    if "cross_validation" in fit.stats:
        result.model.stats["cross_validation"] = fit.stats["cross_validation"]
    _attach_residuals(result, observations, fit.shape)
    report(steps, steps, f"{model}: done")
    return result


def _attach_residuals(result: CalibrationResult, observations: list[TargetObservations],
                      shape: TargetShape) -> None:
    """Inlier residuals per view for the residual plot, with each view's expected RMS."""
    for j, (obs, pose, row) in enumerate(zip(observations, result.poses,
                                             result.stats["per_pose"], strict=True)):
        used = obs.used()
        used[row["outliers"]] = False
        pts, _ = shape.points(obs.target_xyz[used])
        uv = result.model.project(pts @ pose.rotation.T + pose.translation)
        result.residual_pixels[j] = obs.image_xy[used]
        result.residuals[j] = uv - obs.image_xy[used]
        row["pose"] = j
        row["expected_rms_px"] = float(np.sqrt(2) * row["sigma_px"])
