"""sGCC where a parametric family is exact: test it, then centre the spline prior on it.

Why sGCC costs 1.6-2.2x the true family on the same pixels: not bias (its chi2 is 1.00)
but variance. A 10x10 cubic mesh gives each ray component 169 free control points against
the family's 8-12 parameters, and the second-difference prior (weight 1e-10) hardly
constrains them; a stronger plain prior pulls towards *linear* ray fields and biases
(measured: weight 1e-4 -> 3.8x, 1e-2 -> 1700x). The fix keeps the generic model and moves
the prior's centre: a dense parametric fit (`points: "all"`), simplest family first:
opencv5, fisheye, opencv-rational (from sGCC's own OpenCV init). The first that fits as well
as the free spline (a likelihood-ratio test: the spline's chi2 gain within 3 sqrt(2 dof) of
its expectation under the family) is used: the spline is refitted with a strong prior
(weight `PRIOR_WEIGHT`, relative) on its deviation from the family's field, with the
family's parameters left free; its covariance comes from `calibration.fit.sgcc.prior`
(why: docs/generic.md). Otherwise the free fit stands.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from calibration.fit.correspondences import PointSet
from calibration.fit.observations import PoseObs
from calibration.fit.ransac import DegenerateError
from calibration.fit.result import PoseEstimate
from calibration.fit.sgcc.lm import gauge_constraints
from calibration.metrology.lm import fit_dense
from calibration.metrology.refine import fit_parametric_dense
from calibration.metrology.screen import PARAM_NAMES, ScreenModel
from calibration.models.bspline import SplineGrid
from calibration.models.parametric import OpenCVRationalModel

# A family the views do not determine (or OpenCV cannot initialize) is skipped.
_NOT_DETERMINED = (DegenerateError, ValueError, np.linalg.LinAlgError, cv2.error)
PRIOR_WEIGHT = 100.0  # relative to the mean diagonal of the spline normal equations


def _point_sets(obs: list[PoseObs], pitch: np.ndarray) -> list[PointSet]:
    """sGCC observations (mm) as the parametric fits' point sets (screen px)."""
    return [PointSet(o.pixels, o.screen_mm / pitch, o.sigma_mm / pitch, (pitch[0], pitch[1]))
            for o in obs]


def _rational_from_init(pts: list[PointSet], screen: ScreenModel,
                       image_size: tuple[int, int], cv_fit: tuple) -> tuple[Any, list, dict]:
    """Dense opencv-rational fit started from sGCC's own OpenCV init (no second OpenCV run)."""
    k, dist, rvecs, tvecs = cv_fit
    model = OpenCVRationalModel(image_size, k, np.asarray(dist).ravel()[:8])
    poses = [PoseEstimate(cv2.Rodrigues(np.asarray(r, np.float64).reshape(3))[0],
                          np.asarray(t, np.float64).ravel()) for r, t in zip(rvecs, tvecs,
                                                                             strict=True)]
    free = np.zeros(model.get_params().size, dtype=bool)
    free[:12] = True  # K and k1..k6, p1, p2; thin prism stays 0
    dense = fit_dense(model, poses, pts, screen, free)
    std = dict(zip(model.param_names(), dense.param_std.tolist(), strict=True))
    return dense.model, dense.poses, {"reduced_chi2": dense.stats["reduced_chi2"],
                                      "param_std": std, "family": "opencv-rational",
                                      "screen": dense.screen.to_json()}


def _dense(pts: list[PointSet], screen: ScreenModel, image_size: tuple[int, int],
           family: str) -> tuple[Any, list, dict] | None:
    """Dense fit of `family` (OpenCV init) on the same screen model, or None where the views
    do not determine it."""
    try:
        model, poses, _, stats, _ = fit_parametric_dense(
            pts, image_size, family, screen.geometry,
            {"screen": screen.mode, "glass_index": screen.glass_index})
    except _NOT_DETERMINED:
        return None
    return model, poses, {**stats, "family": family}


def family_adequate(family_stats: dict[str, Any], spline_chi2_dof: float, n_residuals: int,
                    extra_dof: int) -> tuple[bool, dict[str, float]]:
    """Likelihood-ratio test: does the spline's extra freedom fit better than noise would?

    Both fits' chi2 are per degree of freedom, so the gain (family minus spline, in chi2
    units) is chi2(extra) - extra under the family: mean 0, std sqrt(2 extra); it must stay
    within 3 std (the expected `extra` itself is already taken out by the dof)."""
    scale = max(spline_chi2_dof, 1e-12)
    gain = (family_stats["reduced_chi2"] - spline_chi2_dof) * n_residuals / scale
    limit = 3.0 * np.sqrt(2.0 * max(extra_dof, 1))
    return bool(gain <= limit), {"chi2_gain": float(gain), "chi2_gain_limit": float(limit)}


def choose_family(obs: list[PoseObs], screen: ScreenModel, grid: SplineGrid, n_comp: int,
                  free_fit_chi2: float, n_residuals: int, cv_fit: tuple
                  ) -> tuple[Any | None, dict[str, Any]]:
    """The first family, simplest first (opencv5, fisheye, rational from `cv_fit`), whose
    dense fit passes the test: (model, verdict); if none passes, the closest with
    `verdict["adequate"]` False (model None if none could be fitted).

    `screen`: the spline's screen model (sGCC's `screen: "fit"` -> mode "fit"): the families
    fit it too, so they are judged on the same model (`verdict["screen"]`: their estimate).
    `free_fit_chi2` / `n_residuals`: the free spline fit's chi2/dof and residual count.
    """
    pts = _point_sets(obs, np.asarray(screen.geometry.pitch_mm, dtype=np.float64))
    n_gauge = len(gauge_constraints(grid, n_comp, grid.size * n_comp))
    best = None
    for fit in (lambda: _dense(pts, screen, grid.image_size, "opencv5"),
                lambda: _dense(pts, screen, grid.image_size, "fisheye"),
                lambda: _rational_from_init(
                    pts, ScreenModel(screen.geometry, screen.mode, screen.glass_index),
                    grid.image_size, cv_fit)):
        try:
            found = fit()
        except _NOT_DETERMINED:
            found = None
        if found is None:
            continue
        model, _, stats = found
        sigmas = {k: v for k, v in stats["param_std"].items() if v > 0 and k in
                  model.param_names()}
        extra = grid.size * n_comp - n_gauge - len(sigmas)
        ok, test = family_adequate(stats, free_fit_chi2, n_residuals, extra)
        info = {"family": stats["family"], "family_chi2_dof": stats["reduced_chi2"],
                "spline_chi2_dof": free_fit_chi2, "extra_dof": extra, **test, "adequate": ok,
                "weight": PRIOR_WEIGHT if ok else None, "param_std": sigmas}
        if screen.mode == "fit":
            info["screen"] = {k: stats["screen"][k] for k in PARAM_NAMES}
        if ok:
            return model, info
        if best is None or test["chi2_gain"] < best[1]["chi2_gain"]:
            best = (model, info)
    if best is None:  # no family could be fitted at all: the free spline stands
        return None, {"family": None, "adequate": False, "weight": None, "param_std": {}}
    return best
