"""sGCC where a parametric family is exact: test it, then centre the spline prior on it.

Why sGCC costs 1.6-2.2x the true family on the same pixels: not bias (its chi2 is 1.00)
but variance. A 10x10 cubic mesh gives each ray component 169 free control points against
the family's 8-12 parameters, and the second-difference prior (weight 1e-10) hardly
constrains them; a stronger plain prior pulls towards *linear* ray fields and biases
(measured: weight 1e-4 -> 3.8x, 1e-2 -> 1700x). The fix keeps the generic model and moves
the prior's centre: a dense parametric fit (`points: "all"`), simplest family first:
opencv5, fisheye, opencv-rational (from sGCC's own OpenCV init). The first that fits as well
as the free spline (a likelihood-ratio test: the spline's chi2 gain within 3 sqrt(2 dof) of
its expectation under the family) is used; a family is first fitted on a grid subset of
the pixels and refused there if it fails the same test on those pixels (paired with the
spline's residuals), and only the survivor is polished on every point and tested exactly.
The spline is then refitted with a strong prior (weight `PRIOR_WEIGHT`, relative) on its
deviation from the family's field, with the family's parameters left free; its covariance
comes from `calibration.fit.sgcc.prior` (why: docs/generic.md). Otherwise the free fit
stands.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from calibration.fit.correspondences import PointSet
from calibration.fit.observations import PoseObs
from calibration.fit.ransac import DegenerateError
from calibration.fit.result import PoseEstimate
from calibration.fit.sgcc.lm import gauge_constraints
from calibration.fit.sgcc.state import LMResult
from calibration.metrology.lm import DenseFit, fit_dense, squared_norms
from calibration.metrology.refine import fit_parametric_dense
from calibration.metrology.screen import PARAM_NAMES, ScreenModel
from calibration.models.bspline import SplineGrid
from calibration.models.parametric import OpenCVRationalModel

# A family the views do not determine (or OpenCV cannot initialize) is skipped.
_NOT_DETERMINED = (DegenerateError, ValueError, np.linalg.LinAlgError, cv2.error)
PRIOR_WEIGHT = 100.0  # relative to the mean diagonal of the spline normal equations
SCREEN_POINTS = 1000  # points per pose (largest pose) the families are first fitted on
_OUTLIER_ROUNDS = 2  # of the dense fits that decide (fit_dense's default)
INIT_POINTS = 500  # points per pose of OpenCV's initial fit of a family


def _point_sets(obs: list[PoseObs], pitch: np.ndarray) -> list[PointSet]:
    """sGCC observations (mm) as the parametric fits' point sets (screen px)."""
    return [PointSet(o.pixels, o.screen_mm / pitch, o.sigma_mm / pitch, (pitch[0], pitch[1]))
            for o in obs]


def _rational_from_init(pts: list[PointSet], screen: ScreenModel,
                       image_size: tuple[int, int], cv_fit: tuple, rounds: int) -> DenseFit:
    """Dense opencv-rational fit started from sGCC's own OpenCV init (no second OpenCV run)."""
    k, dist, rvecs, tvecs = cv_fit
    model = OpenCVRationalModel(image_size, k, np.asarray(dist).ravel()[:8])
    poses = [PoseEstimate(cv2.Rodrigues(np.asarray(r, np.float64).reshape(3))[0],
                          np.asarray(t, np.float64).ravel()) for r, t in zip(rvecs, tvecs,
                                                                             strict=True)]
    free = np.zeros(model.get_params().size, dtype=bool)
    free[:12] = True  # K and k1..k6, p1, p2; thin prism stays 0
    return fit_dense(model, poses, pts, screen, free, outlier_rounds=rounds)


def _dense(pts: list[PointSet], screen: ScreenModel, image_size: tuple[int, int],
           family: str, rounds: int) -> DenseFit:
    """Dense fit of all of `family`'s parameters (opencv5 and fisheye have no optional terms)
    on the same screen model, from OpenCV's fit of `INIT_POINTS` points per pose."""
    model, poses = fit_parametric_dense(
        pts, image_size, family, screen.geometry,
        {"points": "sampled", "max_points_per_pose": INIT_POINTS})[:2]
    return fit_dense(model, poses, pts,
                     ScreenModel(screen.geometry, screen.mode, screen.glass_index),
                     np.ones(model.get_params().size, dtype=bool), outlier_rounds=rounds)


def _stats(fit: DenseFit, family: str) -> dict[str, Any]:
    """What the test and the prior need of a dense fit: chi2/dof, 1-sigma per parameter."""
    return {"reduced_chi2": fit.stats["reduced_chi2"], "family": family,
            "param_std": dict(zip(fit.model.param_names(), fit.param_std.tolist(), strict=True)),
            "screen": fit.screen.to_json()}


def grid_subset(pixels: np.ndarray, stride: int) -> np.ndarray:
    """Indices of the points on every `stride`-th column and row of the pose's own pixel
    lattice (ranks of its distinct u and v): a regular grid over the whole seen area, the
    same fraction (about 1/stride^2) of every region, chosen without looking at the data."""
    cols = np.unique(pixels[:, 0], return_inverse=True)[1]
    rows = np.unique(pixels[:, 1], return_inverse=True)[1]
    return np.flatnonzero((cols % stride == 0) & (rows % stride == 0))


def screen_stride(obs: list[PoseObs], per_pose: int | None = None) -> int:
    """Grid stride leaving about `per_pose` (default `SCREEN_POINTS`) points in the largest
    pose (1: use everything)."""
    per_pose = SCREEN_POINTS if per_pose is None else per_pose
    return max(1, int(np.sqrt(max(len(o.pixels) for o in obs) / per_pose)))


def _spline_squares(obs: list[PoseObs], free: LMResult, index: list[np.ndarray]
                    ) -> list[np.ndarray]:
    """The free spline's whitened squared residuals at `index` of each pose (NaN where it
    rejected the point)."""
    out = []
    for o, r, inl, i in zip(obs, free.residuals, free.inliers, index, strict=True):
        sq = np.sum((r[i] / o.sigma_mm[i]) ** 2, axis=1)
        out.append(np.where(inl[i], sq, np.nan))
    return out


def subset_gain(fit: DenseFit, sub: list[PointSet], spline_sq: list[np.ndarray],
                spline_chi2_dof: float) -> float:
    """Paired chi2 gain of the spline over a family fitted on the subset, on the subset's
    points both keep (chi2 units of the spline's noise scale, as `family_adequate`)."""
    fam = np.concatenate(squared_norms(fit, sub))
    spl = np.concatenate(spline_sq)
    ok = np.isfinite(fam) & np.isfinite(spl)
    return float((fam[ok].sum() - spl[ok].sum()) / max(spline_chi2_dof, 1e-12))


def _limit(extra_dof: int) -> float:
    """3 standard deviations of chi2(extra) - extra."""
    return float(3.0 * np.sqrt(2.0 * max(extra_dof, 1)))


def family_adequate(family_stats: dict[str, Any], spline_chi2_dof: float, n_residuals: int,
                    extra_dof: int) -> tuple[bool, dict[str, float]]:
    """Likelihood-ratio test: does the spline's extra freedom fit better than noise would?

    Both fits' chi2 are per degree of freedom, so the gain (family minus spline, in chi2
    units) is chi2(extra) - extra under the family: mean 0, std sqrt(2 extra); it must stay
    within 3 std (the expected `extra` itself is already taken out by the dof)."""
    scale = max(spline_chi2_dof, 1e-12)
    gain = (family_stats["reduced_chi2"] - spline_chi2_dof) * n_residuals / scale
    limit = _limit(extra_dof)
    return bool(gain <= limit), {"chi2_gain": float(gain), "chi2_gain_limit": limit}


def screen_limit(fraction: float, n_spline: int, n_family: int, n_shared: int) -> float:
    """The largest subset gain (`subset_gain`) of a family that would pass the full test.

    With the family exact, the subset fit leaves chi2 ~ n_S - k (k = n_family + n_shared: its
    parameters with the poses' and screen's, all fitted to the subset) and the spline,
    fitted on every point, leaves n_S - f p on the subset (p = n_spline + n_shared, f the
    subset's fraction of the points: its share of the spline's leverage): gain f p - k, std
    about sqrt(2 (k + f p)). A misfit allowed by the full test adds at most f times its
    limit. Refusing above that plus 5 std never refuses a family the full test accepts."""
    k, p = n_family + n_shared, n_spline + n_shared
    return (fraction * p - k + fraction * _limit(n_spline - n_family)
            + 5.0 * float(np.sqrt(2.0 * (k + fraction * p))))


FamilyFit = Callable[[list[PointSet], int], "DenseFit | None"]  # (points, outlier rounds)


def _attempt(fit: FamilyFit, pts: list[PointSet], rounds: int) -> DenseFit | None:
    """`fit`, or None where the views do not determine the family."""
    try:
        return fit(pts, rounds)
    except _NOT_DETERMINED:
        return None


def _screened(fit: FamilyFit, pts: list[PointSet], sub: list[PointSet] | None,
              spline_sq: list[np.ndarray], free: LMResult, n_spline: int
              ) -> tuple[DenseFit | None, tuple[float, float] | None]:
    """(the family's dense fit, (its subset gain, the screen's limit)): on every point
    (polished from the subset's estimate) if it passes the screen on `sub`, on the subset
    alone if it does not; no gain without a subset or where the subset does not determine
    the family (then fitted on every point directly); fit None where nothing fits."""
    if sub is not None:
        found = _attempt(fit, sub, 0)  # a screening fit needs no second outlier rounds
        if found is not None:
            gain = subset_gain(found, sub, spline_sq, free.chi2_dof)
            fraction = sum(map(len, sub)) / sum(map(len, pts))
            limit = screen_limit(fraction, n_spline, int(np.count_nonzero(found.param_std > 0)),
                                 6 * len(sub) + found.screen.n_free)
            if gain > limit:
                return found, (gain, limit)
            return _attempt(lambda p, r: fit_dense(found.model, found.poses, p, found.screen,
                                                   found.free, outlier_rounds=r),
                            pts, _OUTLIER_ROUNDS), (gain, limit)
    return _attempt(fit, pts, _OUTLIER_ROUNDS), None


def choose_family(obs: list[PoseObs], screen: ScreenModel, grid: SplineGrid, n_comp: int,
                  free: LMResult, cv_fit: tuple) -> tuple[Any | None, dict[str, Any]]:
    """The first family, simplest first (opencv5, fisheye, rational from `cv_fit`), whose
    dense fit passes the test: (model, verdict); if none passes, the closest with
    `verdict["adequate"]` False (model None if none could be fitted).

    Each family is first fitted on a grid subset (`grid_subset`, about `SCREEN_POINTS` per
    pose) and screened there (`subset_gain` against `screen_limit`, docs/generic.md); only
    a family that passes is polished on every point and judged by the exact test
    (`family_adequate`). `screen`: the spline's screen model (sGCC's `screen: "fit"` -> mode
    "fit"): the families fit it too, so they are judged on the same model
    (`verdict["screen"]`: their estimate). `free`: the free spline fit (chi2/dof, residuals
    and inliers on `obs`).
    """
    pts = _point_sets(obs, np.asarray(screen.geometry.pitch_mm, dtype=np.float64))
    n_res = 2 * sum(int(inl.sum()) for inl in free.inliers)
    n_spline = grid.size * n_comp - len(gauge_constraints(grid, n_comp, grid.size * n_comp))
    stride = screen_stride(obs)
    sub, spline_sq, fraction = None, [], 1.0
    if stride > 1:
        index = [grid_subset(o.pixels, stride) for o in obs]
        sub = [p.subset(i) for p, i in zip(pts, index, strict=True)]
        spline_sq = _spline_squares(obs, free, index)
        fraction = sum(map(len, sub)) / sum(map(len, pts))

    def rational(p: list[PointSet], rounds: int) -> DenseFit:
        fresh = ScreenModel(screen.geometry, screen.mode, screen.glass_index)
        return _rational_from_init(p, fresh, grid.image_size, cv_fit, rounds)

    best, refused = None, []
    for family, fit in (
            ("opencv5", lambda p, r: _dense(p, screen, grid.image_size, "opencv5", r)),
            ("fisheye", lambda p, r: _dense(p, screen, grid.image_size, "fisheye", r)),
            ("opencv-rational", rational)):
        found, screened = _screened(fit, pts, sub, spline_sq, free, n_spline)
        if found is None:
            continue
        stats = _stats(found, family)
        sigmas = {k: v for k, v in stats["param_std"].items() if v > 0}
        extra = n_spline - len(sigmas)
        if screened is not None and screened[0] > screened[1]:  # refused on the subset
            info = {"family": family, "extra_dof": extra, "chi2_gain": screened[0],
                    "chi2_gain_limit": screened[1], "tested_on": "subset",
                    "subset_fraction": fraction, "adequate": False, "weight": None,
                    "param_std": sigmas}
            key = screened[0] / fraction  # about the gain on every point
        else:
            ok, test = family_adequate(stats, free.chi2_dof, n_res, extra)
            info = {"family": family, "family_chi2_dof": stats["reduced_chi2"],
                    "spline_chi2_dof": free.chi2_dof, "extra_dof": extra, **test,
                    "tested_on": "all", "subset_fraction": fraction,
                    "subset_chi2_gain": None if screened is None else screened[0],
                    "subset_chi2_gain_limit": None if screened is None else screened[1],
                    "adequate": ok,
                    "weight": PRIOR_WEIGHT if ok else None, "param_std": sigmas}
            if screen.mode == "fit":
                info["screen"] = {k: stats["screen"][k] for k in PARAM_NAMES}
            if ok:
                return found.model, {**info, "refused": refused}
            key = test["chi2_gain"]
        refused.append({k: info[k] for k in ("family", "tested_on", "chi2_gain",
                                             "chi2_gain_limit")})
        if best is None or key < best[2]:
            best = (found.model, info, key)
    if best is None:  # no family could be fitted at all: the free spline stands
        return None, {"family": None, "adequate": False, "weight": None, "param_std": {},
                      "refused": []}
    return best[0], {**best[1], "refused": refused}
