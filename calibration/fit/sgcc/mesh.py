"""Mesh choice for sGCC (option `cells: "auto"`): the coarsest candidate mesh whose predicted
full-data error is within one standard error of the best.

Each candidate is fitted on half of an even subset of the points and scored on the other
half (pixels interleaved with the training ones, poses as fitted). With screen sigmas that
are right, a validation point's chi^2 per residual is 1 + bias^2 + (fit variance), the fit
variance being about k/n (k free parameters, n training residuals). The full fit has N
residuals, so its expected error is bias^2 + k/N: finer meshes pay off when they remove
more bias than they add variance at the full data's size, not the subset's.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from calibration.fit.observations import PoseObs
from calibration.fit.sgcc.initial import OpenCVFit, initial_state
from calibration.fit.sgcc.lm import gauge_constraints, run_lm
from calibration.fit.sgcc.problem import Problem
from calibration.fit.sgcc.robust import sigma_norm
from calibration.fit.sgcc.state import LMOptions
from calibration.models.bspline import SplineGrid

CANDIDATE_CELLS = (10, 14, 20)  # cells along the image's longer side
_VALIDATION_CUT = 8.0  # sigmas: validation points beyond this are outliers, not misfit


def candidate_meshes(image_size: tuple[int, int]) -> list[tuple[int, int]]:
    """Candidate (cu, cv), square-ish cells: `CANDIDATE_CELLS` along the longer side."""
    w, h = image_size
    out = []
    for n in CANDIDATE_CELLS:
        cu, cv = (n, max(4, round(n * h / w))) if w >= h else (max(4, round(n * w / h)), n)
        out.append((cu, cv))
    return out


def _split(obs: list[PoseObs], target: int) -> tuple[list[PoseObs], list[PoseObs]]:
    """Every k-th point of each pose (about 2 x `target` in all), alternately to train and
    validation."""
    k = max(1, sum(len(o.pixels) for o in obs) // max(2 * target, 1))

    def take(o: PoseObs, start: int) -> PoseObs:
        sl = slice(start, None, 2 * k)
        return PoseObs(o.pixels[sl], o.screen_mm[sl], o.sigma_mm[sl])

    return [take(o, 0) for o in obs], [take(o, k) for o in obs]


def choose_mesh(
    obs: list[PoseObs],
    image_size: tuple[int, int],
    n_comp: int,
    lm: LMOptions,
    cv_fit: OpenCVFit,
) -> tuple[tuple[int, int], list[dict[str, float | list[int]]]]:
    """The chosen (cu, cv) and one row per candidate: cells, free parameters, validation
    chi^2 per residual, predicted full-data error and its standard error (sigma^2 units)."""
    train, val = _split(obs, lm.subset_pixels // 2)
    n_train = 2 * sum(len(o.pixels) for o in train)
    n_full = 2 * sum(len(o.pixels) for o in obs)
    rows: list[dict[str, float | list[int]]] = []
    for cells in candidate_meshes(image_size):
        grid = SplineGrid(image_size, cells)
        n_gauge = len(gauge_constraints(grid, n_comp, grid.size * n_comp))
        k = grid.size * n_comp + 6 * len(obs) - n_gauge
        if rows and k > n_train / 10:  # too few points to fit finer meshes on the subset
            break
        out = run_lm(grid, n_comp, train, initial_state(train, grid, n_comp, cv_fit),
                     replace(lm, subset_pixels=n_train))
        prob = Problem(grid, n_comp, val, lm.screen)  # validated through the fitted screen
        res, ok = prob.residuals(out.state)
        s = sigma_norm(prob, res)
        s = s[ok & (s <= _VALIDATION_CUT)]
        chi2 = float(np.mean(s * s) / 2)
        bias2 = chi2 - 1.0 - k / n_train
        rows.append({
            "cells": list(cells),
            "free_parameters": k,
            "validation_chi2": chi2,
            "predicted_error": bias2 + k / n_full,
            "standard_error": float(np.std(s * s / 2) / np.sqrt(len(s))),
        })
    best = min(rows, key=lambda r: r["predicted_error"])
    chosen = next(r for r in rows if r["predicted_error"] <= best["predicted_error"]
                  + best["standard_error"])
    return (int(chosen["cells"][0]), int(chosen["cells"][1])), rows
