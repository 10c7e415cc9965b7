"""Parametric calibration on every decoded pixel: OpenCV initializes, the weighted LM decides.

Options (beside calibration.fit.parametric's): `points` "all" (default: refine on every
valid pixel, weighted by its decoded sigma) or "sampled" (OpenCV's fit on
max_points_per_pose points, the former behaviour); `screen` "flat" (default) or "fit"
(panel bow/twist and cover-glass thickness estimated with the camera); `glass_index`
(default 1.52, taken as known).

An opencv-rational fit that lands where its radial factor is near 0/0 inside the image
(`calibration.uncertainty.radial_pole_margin` under `MIN_POLE_MARGIN`) is refitted from the
opencv5 solution (k4..k6 = 0); the refit is kept when its cost is no worse than the first
fit's beyond noise (`POLE_REFIT_CHI2_RTOL`), and the stats' `fit_note` says what happened.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from calibration.fit.classic.options import ParametricOptions
from calibration.fit.classic.parametric import fit_parametric
from calibration.fit.classic.pnp import estimate_pose
from calibration.fit.correspondences import PointSet
from calibration.fit.registry import model_spec
from calibration.fit.result import PoseEstimate
from calibration.metrology.lm import DenseFit, fit_dense, flat_equivalent
from calibration.metrology.screen import ScreenModel
from calibration.models.parametric import OpenCVRationalModel, PinholeFamily
from calibration.shared.plan import ScreenGeometry
from calibration.uncertainty import MIN_POLE_MARGIN, radial_pole_margin

OWN_KEYS = ("points", "screen", "glass_index")
# A refit away from the pole is kept when its reduced chi-square exceeds the first fit's by
# at most this fraction: the two describe the same rays (the factor's common root cancels),
# so only the optimizer's end point differs, well inside the noise of a per-point sigma.
POLE_REFIT_CHI2_RTOL = 0.01


def split_options(model_name: str, options: ParametricOptions | dict[str, Any] | None
                  ) -> tuple[dict[str, Any], ParametricOptions]:
    """(this module's options, the typed options for the OpenCV stage); ValueError naming
    the bad field (`options.<field>: ...`), as the registry checks requests."""
    opts = model_spec(model_name).parse_options(options)
    return {k: getattr(opts, k) for k in OWN_KEYS}, opts


def _free_mask(model: PinholeFamily, opencv_opts: ParametricOptions) -> np.ndarray:
    """Parameters the refinement fits: all, except thin prism unless asked for."""
    free = np.ones(model.get_params().size, dtype=bool)
    if model.type_name == "opencv-rational" and not opencv_opts.thin_prism:
        free[4 + 8:] = False
    return free


def fit_parametric_dense(
    points: list[PointSet], image_size: tuple[int, int], model_name: str,
    screen: ScreenGeometry, options: ParametricOptions | dict[str, Any] | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> tuple[PinholeFamily, list[PoseEstimate], list[PointSet], dict[str, Any], DenseFit | None]:
    """OpenCV init on sampled points, then (points "all") the weighted LM on every point.

    Returns (model, poses, point sets for flat-screen residual statistics, stats, the dense
    fit or None).
    """
    own, rest = split_options(model_name, options)
    scr = ScreenModel(screen, own["screen"], own["glass_index"])
    model, poses, used, stats = fit_parametric(points, image_size, model_name, rest, progress)
    stats["options"] = {**stats["options"], **own}
    if own["points"] == "sampled":
        stats["screen"] = scr.to_json()
        return model, poses, used, stats, None
    init = model.get_params().copy()
    step = [0]

    def report(msg: str) -> None:
        step[0] += 1
        if progress:
            progress(min(step[0], 9), 10, f"{model_name}: weighted fit, {msg}")

    dense = fit_dense(model, poses, points, scr, _free_mask(model, rest), progress=report)
    note = ""
    margin = radial_pole_margin(dense.model)
    if margin < MIN_POLE_MARGIN:
        dense, note = _away_from_pole(dense, margin, points, image_size, scr, rest, report)
    std = dense.param_std
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(std > 0, (init - dense.model.get_params()) / std, 0.0)
    names = dense.model.param_names()
    stats.update({
        "param_std": dict(zip(names, std.tolist(), strict=True)),
        "reduced_chi2": dense.stats["reduced_chi2"],
        "iterations": stats["iterations"] + dense.stats["iterations"],
        "converged": dense.stats["converged"],
        "screen": dense.screen.to_json(dense.screen_std),
        "dense": {k: dense.stats[k] for k in ("points", "dropped_outliers", "subset_stride",
                                              "iterations", "pose_std")},
        # OpenCV's sampled fit as a cross-check: its parameters in sigmas of the weighted fit.
        "opencv_shift_sigma": dict(zip(names, shift.tolist(), strict=True)),
    })
    if note:
        stats["fit_note"] = note
    return dense.model, dense.poses, flat_equivalent(dense, dense.points), stats, dense


def _away_from_pole(dense: DenseFit, margin: float, points: list[PointSet],
                    image_size: tuple[int, int], screen: ScreenModel,
                    opencv_opts: ParametricOptions, report: Callable[[str], None]
                    ) -> tuple[DenseFit, str]:
    """The weighted rational fit started from the weighted opencv5 fit, when no costlier
    than `dense` (near 0/0 by `margin`) beyond noise; (the fit kept, a note saying which)."""
    five, poses, _, _ = fit_parametric(points, image_size, "opencv5", opencv_opts)
    five_dense = fit_dense(five, poses, points, screen, np.ones(five.get_params().size, bool),
                           progress=report)
    start = OpenCVRationalModel(image_size, five_dense.model.camera_matrix,
                                np.concatenate([five_dense.model.dist, np.zeros(3)]))
    refit = fit_dense(start, five_dense.poses, points, five_dense.screen,
                      _free_mask(start, opencv_opts), progress=report)
    chi_first, chi_refit = dense.stats["reduced_chi2"], refit.stats["reduced_chi2"]
    found = (f"the weighted fit put the radial factor near 0/0 inside the image (margin "
             f"{margin:.2g}), where a first-order ray sigma is not meaningful; a refit from "
             f"the opencv5 solution reaches margin {radial_pole_margin(refit.model):.2g} at "
             f"reduced chi-square {chi_refit:.4g} (first fit {chi_first:.4g})")
    if chi_refit <= chi_first * (1 + POLE_REFIT_CHI2_RTOL):
        return refit, found + ": the refit is kept"
    return dense, found + ": its cost is higher, the first fit is kept"


def heldout_points(dense: DenseFit, points: list[PointSet], rng: np.random.Generator
                   ) -> list[PointSet]:
    """Held-out poses' points moved to where a flat bare screen shows them.

    The correction needs the pose: robust PnP on the raw points first, then the points are
    corrected with that pose (the correction varies slowly with the pose, so one pass is
    enough; `heldout_errors` re-estimates the pose from the corrected points).
    """
    if dense.screen.mode == "flat":
        return points
    poses = []
    for pts in points:
        r, t, _ = estimate_pose(dense.model, pts, rng)
        poses.append(PoseEstimate(r, t))
    return flat_equivalent(dense, points, poses)
