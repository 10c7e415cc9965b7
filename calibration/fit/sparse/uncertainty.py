"""Projection uncertainty of a pixel-space fit, from the intrinsics' covariance (poses and
target shape marginalized).

A ray fixed in the camera frame is projected with perturbed intrinsics: its pixel moves by
J(q) dtheta, J the derivative of the projection over the intrinsics (central differences
through the model itself). Part of that motion is a rotation of the whole camera frame (a
shifted principal point with the poses turned to match): it moves every pixel alike and
says nothing about how the model maps directions relative to each other, so, as when two
models are compared (`phasecal diff`), it is taken out: the stacked motions of the sensor
grid are projected onto the complement of the three small rotations of the frame. What
remains is the covariance of the model's projection up to the frame's orientation.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from calibration.fit.sparse.ray_residual import ray_residual
from calibration.models.base import CameraModel
from calibration.models.sgcc import SGCCBase

SIGMA_GRID = (32, 24)  # (nx, ny) sensor samples of the projection-sigma map
_ROT_STEP = 1e-6  # rad, central differences of the frame rotation
FAR_MM = 1000.0  # a ray stands for its point this far out (for a central model: any point)


def sensor_grid(image_size: tuple[int, int], nx: int, ny: int) -> np.ndarray:
    """(ny*nx, 2) pixel centres of an even grid over the sensor, corners included."""
    w, h = image_size
    uu, vv = np.meshgrid(np.linspace(0, w - 1, nx), np.linspace(0, h - 1, ny))
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def ray_points(model: CameraModel, pixels: np.ndarray) -> np.ndarray:
    """(M, 3) camera-frame points on the rays of `pixels`, `FAR_MM` from their origins."""
    origins, directions = model.unproject(pixels)
    return origins + FAR_MM * directions


def intrinsics_jacobian(model: CameraModel, rays: np.ndarray, free: np.ndarray
                        ) -> np.ndarray:
    """(M, 2, len(free)) derivative of the projections of fixed ray points over the
    intrinsics: closed form for sGCC (hundreds of control values), central differences
    through the model for the parametric ones."""
    if isinstance(model, SGCCBase):
        return ray_residual(model, model.project(rays), rays).d_coeffs[:, :, free]
    base = model.get_params()
    jac = np.empty((len(rays), 2, free.size))
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
    return jac


def rotate(rays: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Rays turned by the rotation vector `omega` (rad)."""
    return rays @ cv2.Rodrigues(np.asarray(omega, dtype=np.float64).reshape(3, 1))[0].T


def rotation_jacobian(model: CameraModel, rays: np.ndarray) -> np.ndarray:
    """(M, 2, 3) derivative of the projections of rays over a small rotation of the frame."""
    jac = np.empty((len(rays), 2, 3))
    for k in range(3):
        step = np.zeros(3)
        step[k] = _ROT_STEP
        jac[:, :, k] = (model.project(rotate(rays, step))
                        - model.project(rotate(rays, -step))) / (2 * _ROT_STEP)
    return jac


def without_rotation(rot_jac: np.ndarray) -> np.ndarray:
    """(2M, 2M) projector onto the complement of the frame rotations' pixel motions."""
    k = rot_jac.reshape(-1, 3)
    return np.eye(k.shape[0]) - k @ np.linalg.pinv(k)


def frame_free_covariance(model: CameraModel, covariance: np.ndarray, rays: np.ndarray
                          ) -> np.ndarray:
    """(2M, 2M) covariance (px^2) of the stacked projections of `rays` (finite ones only),
    the frame's rotation taken out."""
    free = np.flatnonzero(np.diag(covariance) > 0)
    jac = intrinsics_jacobian(model, rays, free).reshape(-1, free.size)
    proj = without_rotation(rotation_jacobian(model, rays))
    pj = proj @ jac
    return pj @ covariance[np.ix_(free, free)] @ pj.T


def projection_covariance(model: CameraModel, covariance: np.ndarray, rays: np.ndarray
                          ) -> np.ndarray:
    """(M, 2, 2) covariance (px^2) of each ray's projection, frame orientation included
    (what two independent fits of one camera differ by)."""
    free = np.flatnonzero(np.diag(covariance) > 0)
    jac = intrinsics_jacobian(model, rays, free)
    return np.einsum("nip,pq,njq->nij", jac, covariance[np.ix_(free, free)], jac)


def projection_sigma_map(model: CameraModel, covariance: np.ndarray,
                         grid: tuple[int, int] = SIGMA_GRID) -> dict[str, Any]:
    """The 1-sigma projection uncertainty (px, RMS per axis, frame rotation taken out) on a
    sensor grid, NaN where the model has no ray, with its median and maximum, as JSON."""
    nx, ny = grid
    pixels = sensor_grid(model.image_size, nx, ny)
    rays = ray_points(model, pixels)
    ok = np.all(np.isfinite(rays), axis=1) & np.all(np.isfinite(model.project(rays)), axis=1)
    sigma = np.full(len(pixels), np.nan)
    if ok.any():
        cov = frame_free_covariance(model, covariance, rays[ok])
        var = np.clip(np.diag(cov), 0, None).reshape(-1, 2)
        sigma[ok] = np.sqrt(0.5 * var.sum(axis=1))
    return {"grid": [nx, ny], "values": sigma.reshape(ny, nx).tolist(),
            "median": float(np.nanmedian(sigma)), "max": float(np.nanmax(sigma))}
