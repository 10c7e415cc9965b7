"""Calibrate generic camera models (sgcc, sgcc-noncentral) from decoded maps.

Entry point `calibrate_generic`; `calibration.fit.dispatch` forwards these model names here.
Options (dict, all optional): `cells` [cu, cv] (default 10x10) or "auto" (`sgcc/mesh.py`: the
coarsest of 10/14/20 cells along the longer side that fits as well as the best, judged on
validation points), `max_iterations` (60),
`huber_k` (3), `cut_sigmas` (8), `smooth` (1e-10, relative weight of the
second-difference prior that only matters where there are no data), `xp` ("numpy": threaded
CPU, default; "cupy": residuals and normal equations on the GPU, `sgcc/device.py`),
`family_prior` ("auto", the default for sgcc on a flat screen: where a dense parametric fit is
as good as the free spline, refit with the prior centred on it, calibration.metrology.
family_prior and calibration.fit.sgcc.prior; "off", the default otherwise), `screen`
("flat", default; "fit": panel bow/twist and cover-glass thickness fitted jointly,
sgcc/screen_terms.py) and `glass_index` (1.52).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from typing import Any

import numpy as np

from calibration.decode.arrays import array_module
from calibration.evaluate import summarize
from calibration.fit.heldout import split_heldout
from calibration.fit.observations import PoseObs, observations
from calibration.fit.registry import model_spec
from calibration.fit.result import CalibrationResult, PoseEstimate
from calibration.fit.sgcc.initial import initial_state, opencv_init, pose_from_model
from calibration.fit.sgcc.lm import run_lm
from calibration.fit.sgcc.mesh import choose_mesh
from calibration.fit.sgcc.options import SgccOptions
from calibration.fit.sgcc.prior import (
    FieldProjector,
    deviation_precision,
    family_tangent,
    prior_covariance,
)
from calibration.fit.sgcc.problem import Problem
from calibration.fit.sgcc.screen_terms import (
    ScreenTrace,
    holds_glass,
    normal_spread_deg,
    screen_stats,
    screen_warnings,
)
from calibration.fit.sgcc.state import LMOptions, LMResult, LMState
from calibration.fit.sgcc.statistics import fit_statistics
from calibration.metrology.family_prior import PRIOR_WEIGHT, choose_family
from calibration.metrology.screen import ScreenModel
from calibration.models.bspline import SplineGrid
from calibration.models.heap import retained_heap
from calibration.models.sgcc import SGCCBase
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import ScreenGeometry
from calibration.shared.progress import CancelCheck, ProgressFn

_FEW_VIEWS = 0.1  # warn when more of the seen pixels than this have fewer than 3 views
_MESH_HINT_RATIO = 1.1  # noise-floor ratio above which a finer mesh is suggested


def _lm_options(opts: SgccOptions) -> LMOptions:
    """LM options from the typed options; a missing CuPy fails here, before any work."""
    try:
        array_module(opts.xp)
    except ValueError as exc:
        raise ValueError(f"options.{exc}") from None
    return LMOptions(max_iterations=opts.max_iterations, huber_k=opts.huber_k,
                     cut_sigmas=opts.cut_sigmas, smooth=opts.smooth, xp=opts.xp)


def _fit(
    cls: type[SGCCBase],
    obs: list[PoseObs],
    grid: SplineGrid,
    init: LMState,
    lm: LMOptions,
    progress: ProgressFn | None,
    cancelled: CancelCheck | None,
    problem: Problem | Future[Problem] | None = None,
) -> tuple[SGCCBase, LMResult]:
    """Run LM (on `problem`, the data's sorted `Problem`, where built already) and wrap the
    converged spline as a model with its covariance."""
    out = run_lm(grid, cls.n_components, obs, init, lm, progress=progress, cancelled=cancelled,
                 problem=problem)
    model = cls(grid.image_size, grid.cells, out.state.coeffs)
    ns = grid.size * cls.n_components
    cov = out.covariance[:ns, :ns]
    model.covariance = 0.5 * (cov + cov.T)  # exactly symmetric, as stored in model.json
    return model, out


def _centred_on_family(
    cls: type[SGCCBase], obs: list[PoseObs], screen: ScreenGeometry, grid: SplineGrid,
    lm: LMOptions, free: tuple[SGCCBase, LMResult], cv_fit: tuple,
    progress: ProgressFn | None, cancelled: CancelCheck | None, problem: Future[Problem],
) -> tuple[SGCCBase, LMResult, dict[str, Any]]:
    """Refit with the prior centred on the best parametric family if it fits as well as the
    free spline (calibration.metrology.family_prior, calibration.fit.sgcc.prior), with the
    covariance of that estimate; else the free fit and the verdict."""
    fitted, out = free
    mode = "flat" if lm.screen is None else "fit"  # the families fit the same screen model
    scr = ScreenModel(screen, mode, 1.52 if lm.screen is None else lm.screen.index)
    family, info = choose_family(obs, scr, grid, cls.n_components, out, cv_fit)
    sigmas = info.pop("param_std")
    if not info["adequate"]:
        return fitted, out, info
    project = FieldProjector(grid, cls.n_components)
    # The family's field, with the free fit's poses and screen (converged on these data, in
    # the same gauge; a family's screen can be wild where the poses hardly determine it).
    st = out.state
    start = LMState(project(family).reshape(grid.size, cls.n_components),
                    [r.copy() for r in st.rc], [t.copy() for t in st.tc], st.screen)
    tangent, index = family_tangent(family, project, sigmas)
    precision = deviation_precision(grid, cls.n_components, tangent)
    centred = replace(lm, smooth=PRIOR_WEIGHT, prior_mean=start.coeffs.ravel(),
                      prior_base=precision)
    fitted, out = _fit(cls, obs, grid, start, centred, progress, cancelled, problem)
    cov = prior_covariance(out, grid, cls.n_components, precision, family, project, tangent,
                           index, np.random.default_rng(0),
                           hold_last=lm.screen is not None and lm.hold_glass)
    ns = fitted.coeffs.size
    fitted.covariance = cov[:ns, :ns]
    return fitted, replace(out, covariance=cov), {**info, "tangent_dims": len(index)}


def _heldout(
    model: SGCCBase, obs: list[PoseObs], indices: list[int], lm: LMOptions, pitch_mm: np.ndarray,
    screen: np.ndarray | None = None,
) -> dict[str, Any]:
    """Pose-only fit of each held-out pose with the model fixed; statistics in the parametric
    models' layout ({per_pose, pooled rms/noise floor}, `evaluate.summarize`)."""
    rows = []
    fixed = LMOptions(
        max_iterations=lm.max_iterations,
        huber_k=lm.huber_k,
        cut_sigmas=lm.cut_sigmas,
        fix_spline=True,
        screen=lm.screen,
    )
    for ob, index in zip(obs, indices, strict=True):
        rc, tc = pose_from_model(model.unproject, ob)
        init = LMState(model.coeffs, [rc], [tc], screen)
        out = run_lm(model.grid, model.n_components, [ob], init, fixed)
        ((_, row),) = fit_statistics(model, out.state.rc, out.state.tc, [ob], out.residuals,
                                     out.inliers, pitch_mm)
        rows.append({"pose": index, **row, "chi2_dof": out.chi2_dof})
    return {"per_pose": rows, **summarize(rows)}


def uncovered_cells(grid: SplineGrid, obs: list[PoseObs]) -> list[int]:
    """Flat indices of spline cells that contain no decoded point in any pose."""
    hit = np.zeros(grid.cells[0] * grid.cells[1], dtype=bool)
    for ob in obs:
        hit[grid.local(ob.pixels[:, 0], ob.pixels[:, 1])[0]] = True  # no basis weights
    return np.flatnonzero(~hit).tolist()


def views_per_pixel(maps: Sequence[DecodedMaps]) -> list[float]:
    """Fractions of the image's pixels seen by 0, 1, 2 and >= 3 of the poses."""
    count = np.sum([m.mask for m in maps], axis=0)
    return (np.bincount(np.minimum(count, 3).ravel(), minlength=4) / count.size).tolist()


def fit_warnings(
    model: str, views: list[float], n_uncovered: int, grid: SplineGrid, noise_ratio: float
) -> list[str]:
    """Plain-language warnings about the pose design and the mesh, for the CLI and reports."""
    out = []
    seen = 1.0 - views[0]
    if model == "sgcc-noncentral" and seen > 0 and (views[1] + views[2]) / seen > _FEW_VIEWS:
        out.append(
            f"{100 * (views[1] + views[2]) / seen:.0f}% of the pixels that saw the screen saw it "
            "in fewer than 3 poses: a non-central ray there trades its origin against its "
            "direction and is poorly determined (see ray_std); add poses that cover the whole "
            "image, at different distances (docs/generic.md, pose design)"
        )
    if n_uncovered:
        out.append(
            f"{n_uncovered} of {grid.cells[0] * grid.cells[1]} spline cells have no data: rays "
            "there are extrapolated by the smoothness prior (their ray_std is large)"
        )
    if noise_ratio > _MESH_HINT_RATIO:
        cu, cv = grid.cells
        out.append(
            f"residuals are {noise_ratio:.2f}x the noise floor: the {cu}x{cv} mesh may be too "
            f"coarse for this lens (try --option cells=[{2 * cu},{2 * cv}]), or the decoded "
            "sigmas are too small"
        )
    return out


def calibrate_generic(
    maps: Sequence[DecodedMaps],
    screen: ScreenGeometry,
    model: str,
    *,
    options: SgccOptions | dict[str, Any] | None = None,
    heldout: Sequence[int] | None = None,
    progress: ProgressFn | None = None,
    cancelled: CancelCheck | None = None,
) -> CalibrationResult:
    """Fit an sGCC model to the poses not in `heldout` (indices); held-out poses are validated.

    `progress(done, total, message)` is called once per LM iteration; `cancelled()`
    returning True aborts with `calibration.shared.progress.Cancelled`.
    """
    spec = model_spec(model)
    if spec.family != "sgcc":
        raise ValueError(f"model: expected an sGCC model (sgcc, sgcc-noncentral), got {model!r}")
    opts: SgccOptions = spec.parse_options(options)
    with retained_heap():  # page faults of the large per-pixel arrays, models/heap.py
        return _calibrate(maps, screen, model, opts, heldout, progress, cancelled)


def _calibrate(
    maps: Sequence[DecodedMaps],
    screen: ScreenGeometry,
    model: str,
    opts: SgccOptions,
    heldout: Sequence[int] | None,
    progress: ProgressFn | None,
    cancelled: CancelCheck | None,
) -> CalibrationResult:
    """Body of `calibrate_generic`."""
    spec = model_spec(model)
    maps, held_maps, held = split_heldout(maps, heldout, "generic")
    t0 = time.perf_counter()
    cells, lm = opts.cells, _lm_options(opts)
    if opts.screen == "fit":
        lm = replace(lm, screen=ScreenTrace.of(screen, opts.glass_index))
    # Default: the family prior for sgcc on a flat screen (with a fitted screen a weakly
    # determined glass trades against the family's field: docs/generic.md).
    prior_mode = opts.family_prior or ("auto" if model == "sgcc" and opts.screen == "flat"
                                       else "off")
    h, w = maps[0].shape
    obs = observations(maps, screen)
    for j, ob in enumerate(obs):
        if len(ob.pixels) < 100:
            raise ValueError(f"maps[{j}]: only {len(ob.pixels)} valid pixels; need >= 100")
    cls = spec.model_class
    with ThreadPoolExecutor(1) as pool:  # the data are sorted while the start is computed
        problem = None if cells == "auto" else pool.submit(
            Problem, SplineGrid((w, h), cells), cls.n_components, obs, lm.screen)
        cv_fit = opencv_init(obs, (w, h))
        spread = normal_spread_deg(cv_fit[2])  # between the initial poses' screen normals
        if lm.screen is not None:
            lm = replace(lm, hold_glass=holds_glass(cls.n_components, spread))
        mesh_choice = None
        if cells == "auto":
            cells, mesh_choice = choose_mesh(obs, (w, h), cls.n_components, lm, cv_fit)
            problem = pool.submit(Problem, SplineGrid((w, h), cells), cls.n_components, obs,
                                  lm.screen)
        grid = SplineGrid((w, h), cells)
        init = initial_state(obs, grid, cls.n_components, cv_fit)
        fitted, out = _fit(cls, obs, grid, init, lm, progress, cancelled, problem)
        prior = None
        if prior_mode == "auto":
            fitted, out, prior = _centred_on_family(cls, obs, screen, grid, lm, (fitted, out),
                                                    cv_fit, progress, cancelled, problem)
        del problem  # its per-pixel arrays are not needed by the statistics
    pitch = np.asarray(screen.pitch_mm, dtype=np.float64)
    n_residuals = 2 * sum(int(inl.sum()) for inl in out.inliers)
    dof_shrink = max(1.0 - (fitted.coeffs.size + 6 * len(obs)) / n_residuals, 0.0)
    poses, per_pose, res_px, pix_out = [], [], {}, {}
    stats_of = fit_statistics(fitted, out.state.rc, out.state.tc, obs, out.residuals,
                              out.inliers, pitch, dof_shrink)
    for j, (px, row) in enumerate(stats_of):
        rc, tc = out.state.rc[j], out.state.tc[j]
        poses.append(PoseEstimate(rc.T, -rc.T @ tc, row["rms_px"], row["rms_screen_px"],
                                  row["n_points"]))
        per_pose.append({"pose": j, **row})
        res_px[j], pix_out[j] = px, obs[j].pixels[out.inliers[j]]
    sample = np.stack(
        np.meshgrid(np.linspace(0, w - 1, 33), np.linspace(0, h - 1, 25)), -1
    ).reshape(-1, 2)
    ang, org = fitted.ray_std(sample)
    uncovered, views = uncovered_cells(grid, obs), views_per_pixel(maps)
    stats: dict[str, Any] = {
        "model": model,
        **summarize(per_pose),
        "per_pose": per_pose,
        "iterations": out.iterations,
        "converged": out.converged,
        "cost": out.cost,
        "cost_history": out.history,
        "chi2_dof": out.chi2_dof,
        "gauge_min_eig": out.min_eig,
        "cells": list(grid.cells),
        "uncovered_cells": uncovered,
        "views_per_pixel": views,
        "ray_std_rad_median": float(np.median(ang)),
        "ray_std_rad_max": float(np.max(ang)),
        "origin_std_mm_median": float(np.median(org)),
        "param_std": {"ray_angle_rad_median": float(np.median(ang))},
    }
    stats["screen"] = screen_stats(screen, opts.screen, opts.glass_index, out.state.screen,
                                   out.covariance, cls.n_components, spread, lm.hold_glass)
    if mesh_choice is not None:
        stats["mesh_choice"] = mesh_choice
    if prior is not None:
        stats["family_prior"] = prior
    stats["warnings"] = fit_warnings(model, views, len(uncovered), grid,
                                     stats["noise_floor_ratio"]) + screen_warnings(stats["screen"])
    if held_maps:
        stats["heldout"] = _heldout(fitted, observations(held_maps, screen), held, lm, pitch,
                                    out.state.screen)
    stats["wall_s"] = time.perf_counter() - t0
    fitted.stats = stats
    return CalibrationResult(fitted, poses, stats, pix_out, res_px)
