"""Fit the smooth generic models (sgcc, sgcc-noncentral) to sparse target observations.

The same maximum-likelihood fit as the parametric one (calibration/fit/sparse/fit.py), and
through the same robust loop: residuals in pixels weighted by weight / sigma (sigma from
the files, or estimated from the residuals), outliers beyond `outlier_sigma` robust sigmas
dropped until the set is stable, the optional target bow, and the covariance from the
inverse normal matrix. What differs:

- residual: the ray-space miss turned into pixels by the spline's local Jacobian
  (`ray_residual.py`), exact derivatives without the model's iterative projection;
- mesh: chosen for the data: the finest mesh (`MESH_CELLS` along the sensor's longer side)
  whose cells that hold points hold `MIN_POINTS_PER_CELL` of them on average; too few
  points for the coarsest is refused with the count needed;
- start: the parametric (opencv5) pixel-space fit of the same observations, its rays
  sampled in the cells that hold points and fitted by the spline, its poses, bow, sigma
  and outliers, all turned into the sGCC gauge (the ray at the sensor centre is +z, the
  row through it stays in the x-z plane: `sgcc/lm.py: gauge_constraints`);
- prior: a weak second-difference prior on the control net (sigma `PRIOR_RELATIVE` of one
  cell's angular size; `PRIOR_ORIGIN_MM` for origins) defines control points that no point
  reaches; its precision is part of the normal matrix, so there the uncertainty is the
  prior's and says so.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from calibration.fit.registry import model_spec
from calibration.fit.sgcc.gauge import GaugeBasis
from calibration.fit.sgcc.initial import gauge_rotation
from calibration.fit.sgcc.lm import gauge_constraints
from calibration.fit.sparse.fit import (
    ObservationFitError,
    SparseFit,
    View,
    collect_views,
    covariance_of,
    fit_observations,
    robust_fit,
    view_statistics,
)
from calibration.fit.sparse.options import MIN_VIEWS, ObservationOptions
from calibration.fit.sparse.ray_residual import ray_residual
from calibration.fit.sparse.target_shape import TargetShape
from calibration.models.bspline import SplineGrid, second_differences
from calibration.models.sgcc import SGCCBase, logmap
from calibration.shared.observations import TargetObservations

MESH_CELLS = (10, 8, 6, 5, 4)  # candidate cells along the longer side, finest first
MIN_POINTS_PER_CELL = 20  # 40 residuals for about one new control point (2-4 values) a cell
START_MODEL = "opencv5"
PRIOR_RELATIVE = 0.1  # second difference of the direction net, in cell angular sizes
PRIOR_ORIGIN_MM = 1.0  # second difference of the origin net (non-central)
_START_SAMPLES_PER_CELL = 6  # ray samples along each axis of each cell with points


def is_sgcc(model_name: str) -> bool:
    """Whether the registry's `model_name` is an sGCC model (family "sgcc")."""
    return model_spec(model_name).family == "sgcc"


def mesh_for(points: np.ndarray, image_size: tuple[int, int], n_views: int,
             cells: tuple[int, int] | str = "auto") -> tuple[tuple[int, int], dict[str, Any]]:
    """(cu, cv) for the inlier pixels `points` (N, 2) of `n_views` views and how it was
    chosen; the finest candidate meeting `MIN_POINTS_PER_CELL`, or `cells` when given."""
    w, h = image_size
    rows = []
    shapes = ([tuple(cells)] if cells != "auto" else
              [(n, max(3, round(n * h / w))) if w >= h else (max(3, round(n * w / h)), n)
               for n in MESH_CELLS])
    for cu, cv in shapes:
        grid = SplineGrid(image_size, (int(cu), int(cv)))
        counts = np.bincount(grid.cell_of(points[:, 0], points[:, 1]), minlength=cu * cv)
        held = counts[counts > 0]
        rows.append({"cells": [int(cu), int(cv)], "cells_with_points": int(held.size),
                     "points_per_cell": float(held.mean())})
        if cells != "auto" or rows[-1]["points_per_cell"] >= MIN_POINTS_PER_CELL:
            return (int(cu), int(cv)), {"candidates": rows,
                                        "min_points_per_cell": MIN_POINTS_PER_CELL}
    coarsest = rows[-1]
    need = MIN_POINTS_PER_CELL * coarsest["cells_with_points"]
    more = int(np.ceil((need - len(points)) * n_views / len(points)))
    raise ObservationFitError(
        f"observations: {len(points)} points in {n_views} views are too few for an sGCC mesh: "
        f"its coarsest, {coarsest['cells'][0]}x{coarsest['cells'][1]} cells, needs >= "
        f"{MIN_POINTS_PER_CELL} points per cell, >= {need} over the "
        f"{coarsest['cells_with_points']} cells they cover (add about {more} "
        f"view{'s' * (more != 1)} like these, or fit a parametric model)")


def spline_gauge(model: SGCCBase) -> GaugeBasis:
    """The free directions of the model's coefficients: those that keep the sGCC gauge (the
    ray at the sensor centre +z, the row through it in the x-z plane; the origin there 0),
    so that a fit moving them cannot also turn or shift the camera frame."""
    cons = gauge_constraints(model.grid, model.n_components, model.coeffs.size)
    return GaugeBasis.null_space_of(cons)


def spline_prior(model: SGCCBase) -> np.ndarray:
    """Whitened prior rows (rows, size*C) over `model.get_params()`: each component's second
    differences over the control net divided by its sigma (`PRIOR_RELATIVE` of one cell's
    angular size for directions, `PRIOR_ORIGIN_MM` for origins). They define the control
    points no observed point reaches."""
    c = model.n_components
    d = second_differences(model.grid)
    cell = max(model.grid.cell_px)
    _, du, dv = model.components(np.array([[(s - 1) / 2 for s in model.image_size]]),
                                 derivatives=True)
    rad_per_px = float(np.hypot(du[0, 0], dv[0, 1]) / np.sqrt(2))
    sigmas = [PRIOR_RELATIVE * cell * rad_per_px] * 2 + [PRIOR_ORIGIN_MM] * (c - 2)
    rows = np.zeros((d.shape[0] * c, model.coeffs.size))
    for comp, s in enumerate(sigmas):
        rows[comp * d.shape[0]:(comp + 1) * d.shape[0], comp::c] = d / s
    return rows


class _SgccProblem:  # a SparseProblem (calibration/fit/sparse/fit.py)
    """Parameter vector [spline in the gauge's free directions, target shape, (rvec, tvec)
    per view]; whitened pixel residuals of the inliers, then the prior's rows."""

    def __init__(self, model: SGCCBase, views: list[View], shape: TargetShape) -> None:
        self.model, self.views, self.shape = model, views, shape
        self.gauge = spline_gauge(model)
        self.z = np.stack([self.gauge.expand(e) for e in np.eye(self.gauge.size)], axis=1)
        self.nz, self.ns = self.gauge.size, shape.n_free
        self.basis = [model.grid.basis(v.xy[:, 0], v.xy[:, 1], derivatives=True)
                      for v in views]
        self.prior = spline_prior(model) @ self.z

    def pack(self) -> np.ndarray:
        return np.concatenate([self.gauge.reduce_vector(self.model.get_params()), self.shape.params,
                               *[np.concatenate([v.rvec, v.tvec]) for v in self.views]])

    def unpack(self, x: np.ndarray) -> None:
        self.model.set_params(self.gauge.expand(x[:self.nz]))
        self.shape.params = x[self.nz:self.nz + self.ns].copy()
        for j, v in enumerate(self.views):
            o = self.nz + self.ns + 6 * j
            v.rvec, v.tvec = x[o:o + 3].copy(), x[o + 3:o + 6].copy()

    def evaluate(self, x: np.ndarray, want_jac: bool, all_points: bool = False
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        """Whitened residuals (inliers, or every used point) and prior rows, and, if asked,
        the Jacobian."""
        self.unpack(x)
        res, jacs = [], []
        n, nz, ns = x.size, self.nz, self.ns
        for j, (v, basis) in enumerate(zip(self.views, self.basis, strict=True)):
            keep = np.ones(v.rows.size, bool) if all_points else v.inlier
            pts, d_shape = self.shape.points(v.xyz[keep])
            rot, d_rot = cv2.Rodrigues(v.rvec)
            cam = pts @ rot.T + v.tvec
            rr = ray_residual(self.model, v.xy[keep], cam, tuple(b[keep] for b in basis))
            s = (v.weight[keep] / v.sigma)[:, None]
            res.append((rr.pixels * s).ravel())
            if want_jac:
                jac = np.zeros((cam.shape[0], 2, n))
                g = self.gauge  # Z's sparsity: most columns pass through, a few mix
                jac[:, :, :nz] = np.concatenate([rr.d_coeffs[:, :, g.keep],
                                                 rr.d_coeffs[:, :, g.mixed] @ g.basis], axis=2)
                if ns:
                    jac[:, :, nz:nz + ns] = np.einsum("nij,jk,nks->nis", rr.d_point, rot,
                                                      d_shape)
                o = nz + ns + 6 * j
                d_cam_rvec = np.einsum("kij,nj->nik", d_rot.reshape(3, 3, 3), pts)
                jac[:, :, o:o + 3] = rr.d_point @ d_cam_rvec
                jac[:, :, o + 3:o + 6] = rr.d_point
                jacs.append((jac * s[:, :, None]).reshape(-1, n))
        res.append(self.prior @ x[:nz])
        if want_jac:
            prior = np.zeros((self.prior.shape[0], n))
            prior[:, :nz] = self.prior
            jacs.append(prior)
        return np.concatenate(res), (np.concatenate(jacs) if want_jac else None)


def _start(model_cls: type[SGCCBase], start: SparseFit, views: list[View],
           cells: tuple[int, int]) -> SGCCBase:
    """The sGCC model sampling the parametric start's rays in the cells that hold points,
    in the sGCC gauge; the views' poses turned to match."""
    size = start.model.image_size
    model = model_cls(size, cells)
    grid = model.grid
    w, h = size
    centre = np.array([[(w - 1) / 2, (h - 1) / 2], [(w - 1) / 2 + 1.0, (h - 1) / 2]])
    _, dc = start.model.unproject(centre)
    q = gauge_rotation(dc[0], dc[1] - dc[0])
    inl = np.concatenate([v.xy[v.inlier] for v in views])
    held = np.unique(grid.cell_of(inl[:, 0], inl[:, 1]))
    cu, cv = grid.cells
    t = (np.arange(_START_SAMPLES_PER_CELL) + 0.5) / _START_SAMPLES_PER_CELL
    iv, iu = np.divmod(held, cu)
    su = ((iu[:, None] + t[None, :]) * w / cu - 0.5)
    sv = ((iv[:, None] + t[None, :]) * h / cv - 0.5)
    pix = np.stack([np.repeat(su, t.size, axis=1).ravel(),
                    np.tile(sv, (1, t.size)).ravel()], axis=1)
    _, d = start.model.unproject(pix)
    ok = np.all(np.isfinite(d), axis=1) & (d[:, 2] > 0)
    coeffs = np.zeros_like(model.coeffs)
    coeffs[:, :2] = grid.fit(pix[ok, 0], pix[ok, 1], logmap(d[ok] @ q.T))
    cons = gauge_constraints(grid, model.n_components, coeffs.size)
    x = coeffs.ravel()
    model.set_params(x - cons.T @ np.linalg.solve(cons @ cons.T, cons @ x))
    for v, pose in zip(views, start.poses, strict=True):
        v.rvec = np.ravel(cv2.Rodrigues(q @ pose.rotation)[0])
        v.tvec = q @ pose.translation
    return model


def fit_sgcc_observations(
    observations: list[TargetObservations], model_name: str,
    options: ObservationOptions | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> SparseFit:
    """Fit `model_name` (sgcc or sgcc-noncentral) to the views; see the module docstring."""
    opts = options or ObservationOptions()
    if not is_sgcc(model_name):
        raise ObservationFitError(f"model: {model_name!r} is not an sGCC model")
    if len(observations) < MIN_VIEWS:
        raise ObservationFitError(f"observations: {model_name} needs >= {MIN_VIEWS} views, "
                                  f"got {len(observations)}")
    t0 = time.perf_counter()
    start = fit_observations(observations, START_MODEL, opts)
    views = collect_views(observations, opts.weights)
    for v, row in zip(views, start.stats["per_pose"], strict=True):
        v.inlier = ~np.isin(v.rows, row["outliers"])
        v.sigma = row["sigma_px"]
    cells, mesh = mesh_for(np.concatenate([v.xy[v.inlier] for v in views]),
                           start.model.image_size, len(views), opts.cells)
    model = _start(model_spec(model_name).model_class, start, views, cells)
    problem = _SgccProblem(model, views, start.shape)
    nfev, rounds, converged = robust_fit(problem, opts, model_name, progress)
    cov = covariance_of(problem)
    nz, ns = problem.nz, problem.ns
    model.covariance = problem.z @ cov[:nz, :nz] @ problem.z.T
    problem.shape.set_covariance(cov[nz:nz + ns, nz:nz + ns])
    poses, stats = view_statistics(problem, [cv2.Rodrigues(v.rvec)[0] for v in views])
    chi2, n_res = stats.pop("reduced_chi2_sum"), stats.pop("residual_count")
    stats.update({
        "reduced_chi2": chi2 / max(n_res - cov.shape[0], 1),
        "mesh": mesh,
        "start": {"model": START_MODEL, "rms_px": start.stats["rms_px"]},
        "target": problem.shape.to_json(),
        "options": opts.model_dump(),
        "iterations": nfev, "outlier_rounds": rounds, "converged": converged,
        "training_poses": list(range(len(views))), "wall_s": time.perf_counter() - t0,
    })
    return SparseFit(model, poses, problem.shape, model.covariance,
                     np.ones(model.coeffs.size, bool), stats)


def fit_sparse(observations: list[TargetObservations], model_name: str,
               options: ObservationOptions | None = None,
               progress: Callable[[int, int, str], None] | None = None) -> SparseFit:
    """The pixel-space fit of any model that takes observations: sGCC here, a parametric
    model in `fit_observations`."""
    fit = fit_sgcc_observations if is_sgcc(model_name) else fit_observations
    return fit(observations, model_name, options, progress)
