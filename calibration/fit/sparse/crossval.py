"""Cross-validation of a pixel-space fit: fit disjoint sets of views, compare the models'
projections across the image with the difference their uncertainties predict.

At each sensor grid pixel q, the ray of model A through q is projected by model B:
d(q) = B(A^-1(q)) - q. If both fits are right and their covariances honest, d is a
zero-mean Gaussian with covariance Sigma_A(q) + Sigma_B(q) (the projection covariances of a
ray fixed in the camera frame, `uncertainty.projection_covariance`: each fit's frame
orientation is as uncertain as its principal point, and both differences and predictions
include it), so z^2 = d^T (Sigma_A + Sigma_B)^-1 d averages 2. The verdict compares
ratio = sqrt(mean z^2 / 2), the difference in units of its prediction, with `AGREE_RATIO`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.fit.sparse.fit import SparseFit
from calibration.fit.sparse.options import MIN_VIEWS, ObservationOptions
from calibration.fit.sparse.sgcc import fit_sparse
from calibration.fit.sparse.uncertainty import (
    SIGMA_GRID,
    projection_covariance,
    ray_points,
    sensor_grid,
)
from calibration.shared.observations import TargetObservations

# differences up to twice their predicted size still agree: the prediction counts the corner
# noise, not the detector's systematic errors (a statistical 99 % bound would be ~1.4)
AGREE_RATIO = 2.0


def split_views(count: int, folds: int) -> list[list[int]]:
    """Disjoint view sets, interleaved (view i goes to fold i mod folds), so each set spans
    the session's poses."""
    return [list(range(k, count, folds)) for k in range(folds)]


def compare_fits(a: SparseFit, b: SparseFit, grid: tuple[int, int] = SIGMA_GRID
                 ) -> dict[str, Any]:
    """Observed against predicted projection difference of two fits of one camera."""
    nx, ny = grid
    pixels = sensor_grid(a.model.image_size, nx, ny)
    rays = ray_points(a.model, pixels)
    with np.errstate(invalid="ignore"):
        ok = np.all(np.isfinite(rays), axis=1) & np.all(np.isfinite(b.model.project(rays)),
                                                        axis=1)
    if not ok.any():
        raise ValueError("cross-validation: the two models share no pixel with a ray")
    q, ray = pixels[ok], rays[ok]
    diff = b.model.project(ray) - q
    cov = (projection_covariance(a.model, a.intrinsics_covariance, ray)
           + projection_covariance(b.model, b.intrinsics_covariance, ray))
    z2 = np.einsum("ni,nij,nj->n", diff, np.linalg.inv(cov), diff)
    ratio = float(np.sqrt(np.mean(z2) / 2))
    norm = np.hypot(diff[:, 0], diff[:, 1])
    predicted = np.sqrt(np.trace(cov, axis1=1, axis2=2))
    diff_map = np.full(len(pixels), np.nan)
    diff_map[ok] = norm
    return {
        "grid": [nx, ny],
        "difference_px": diff_map.reshape(ny, nx).tolist(),
        "rms_difference_px": float(np.sqrt(np.mean(norm**2))),
        "max_difference_px": float(norm.max()),
        "rms_predicted_px": float(np.sqrt(np.mean(predicted**2))),
        "ratio": ratio,
        "agree_ratio": AGREE_RATIO,
        "verdict": "agree" if ratio <= AGREE_RATIO else "disagree",
    }


def cross_validate(observations: list[TargetObservations], model_name: str,
                   options: ObservationOptions, folds: int = 2) -> dict[str, Any]:
    """Fit `folds` disjoint view sets and compare the first two (every pair for more)."""
    if folds < 2:
        raise ValueError(f"cross-validate: expected >= 2 folds, got {folds}")
    sets = split_views(len(observations), folds)
    if min(len(s) for s in sets) < MIN_VIEWS:
        raise ValueError(f"cross-validate: {folds} folds of {len(observations)} views leave "
                         f"{min(len(s) for s in sets)} views in one (need >= {MIN_VIEWS})")
    fits = [fit_sparse([observations[i] for i in s], model_name, options) for s in sets]
    pairs = []
    for i in range(folds):
        for j in range(i + 1, folds):
            pairs.append({"folds": [i, j], **compare_fits(fits[i], fits[j])})
    worst = max(pairs, key=lambda p: p["ratio"])
    return {"folds": sets, "fold_rms_px": [f.stats["rms_px"] for f in fits], "pairs": pairs,
            "ratio": worst["ratio"], "verdict": worst["verdict"]}
