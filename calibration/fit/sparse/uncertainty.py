"""Projection uncertainty of a pixel-space fit: how far (camera px, 1 sigma) the model's
projection of a fixed ray may be off, from the intrinsics' covariance (poses and target
shape marginalized). The ray through pixel q is held fixed and projected with perturbed
intrinsics: Sigma(q) = J(q) C J(q)^T, J the derivative of the projection over the
intrinsics (central differences through the model itself)."""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.models.parametric import PinholeFamily

SIGMA_GRID = (32, 24)  # (nx, ny) sensor samples of the projection-sigma map


def sensor_grid(image_size: tuple[int, int], nx: int, ny: int) -> np.ndarray:
    """(ny*nx, 2) pixel centres of an even grid over the sensor, corners included."""
    w, h = image_size
    uu, vv = np.meshgrid(np.linspace(0, w - 1, nx), np.linspace(0, h - 1, ny))
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def projection_covariance(model: PinholeFamily, covariance: np.ndarray,
                          pixels: np.ndarray) -> np.ndarray:
    """(N, 2, 2) covariance (px^2) of the projection of each pixel's ray; NaN where the
    model has no ray."""
    _, rays = model.unproject(pixels)
    base = model.get_params()
    free = np.flatnonzero(np.diag(covariance) > 0)
    jac = np.empty((len(pixels), 2, free.size))
    try:
        for col, i in enumerate(free):
            step = 1e-6 * max(abs(base[i]), 1e-3)
            v = base.copy()
            v[i] += step
            model.set_params(v)
            plus = model.project(rays)
            v[i] -= 2 * step
            model.set_params(v)
            jac[:, :, col] = (plus - model.project(rays)) / (2 * step)
    finally:
        model.set_params(base)
    c = covariance[np.ix_(free, free)]
    return np.einsum("nip,pq,njq->nij", jac, c, jac)


def intrinsics_covariance(model: PinholeFamily) -> np.ndarray:
    """The covariance a pixel-space fit stored in the model's statistics."""
    entry = model.stats.get("intrinsics_covariance")
    if not isinstance(entry, dict) or entry.get("names") != model.param_names():
        raise ValueError(f"model {model.type_name}: no intrinsics covariance in its stats "
                         "(fitted to observations?)")
    return np.asarray(entry["matrix"], dtype=np.float64)


def projection_sigma_map(model: PinholeFamily, covariance: np.ndarray,
                         grid: tuple[int, int] = SIGMA_GRID) -> dict[str, Any]:
    """The 1-sigma projection uncertainty (px, sqrt of the covariance's trace / 2: the RMS
    per axis) on a sensor grid, with its median and maximum, as JSON data."""
    nx, ny = grid
    cov = projection_covariance(model, covariance, sensor_grid(model.image_size, nx, ny))
    sigma = np.sqrt(0.5 * np.trace(cov, axis1=1, axis2=2))
    return {"grid": [nx, ny], "values": sigma.reshape(ny, nx).tolist(),
            "median": float(np.nanmedian(sigma)), "max": float(np.nanmax(sigma))}
