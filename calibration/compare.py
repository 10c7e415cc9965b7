"""Model-to-model differences: ray angles after the best rotation, the sGCC gauge frame, and
whitened errors of a fitted sGCC model against a known ray field."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from calibration.fit.sgcc.lm import gauge_constraints
from calibration.models.sgcc import SGCCBase, logmap

RayFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]  # pixels (N,2) -> (o, d)


def best_rotation(d_from: np.ndarray, d_to: np.ndarray) -> np.ndarray:
    """Rotation R minimizing sum |R d_from - d_to|^2 over unit vectors (N,3) (Kabsch)."""
    u, _, vt = np.linalg.svd(d_to.T @ d_from)
    s = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    return u @ s @ vt


def ray_angle_difference(
    rays_a: RayFn,
    rays_b: RayFn,
    image_size: tuple[int, int],
    step_px: float = 4.0,
    pixels: np.ndarray | None = None,
) -> dict[str, np.ndarray | float]:
    """Angle (rad) between two models' rays on a pixel grid, after the best aligning rotation.

    Returns the grid `pixels` (N,2), per-pixel `angle_rad` (NaN where either model has no
    ray), `rotation` (b-frame from a-frame), and the `rms_rad` / `max_rad` summary.
    `pixels` (N,2), if given, replaces the grid (e.g. only pixels that saw the target).
    """
    if pixels is None:
        w, h = image_size
        uu, vv = np.meshgrid(np.arange(0, w, step_px), np.arange(0, h, step_px))
        pix = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
    else:
        pix = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    _, da = rays_a(pix)
    _, db = rays_b(pix)
    ok = np.all(np.isfinite(da), axis=1) & np.all(np.isfinite(db), axis=1)
    if ok.sum() < 3:
        raise ValueError("ray_angle_difference: fewer than 3 pixels where both models have rays")
    rot = best_rotation(da[ok], db[ok])
    ang = np.full(len(pix), np.nan)
    cross = np.linalg.norm(np.cross(da[ok] @ rot.T, db[ok]), axis=1)
    dot = np.sum((da[ok] @ rot.T) * db[ok], axis=1)
    ang[ok] = np.arctan2(cross, dot)
    return {
        "pixels": pix,
        "angle_rad": ang,
        "rotation": rot,
        "rms_rad": float(np.sqrt(np.mean(ang[ok] ** 2))),
        "max_rad": float(np.max(ang[ok])),
    }


def sgcc_gauge_transform(
    rays: RayFn, image_size: tuple[int, int], central: bool
) -> tuple[np.ndarray, np.ndarray]:
    """(Q, t) moving a camera's frame into the sGCC gauge (calibration.fit.sgcc.lm docstring).

    Q: center ray to +z, its u-derivative into the x-z plane. t (non-central only): after
    sliding origins to z = 0, ox(c) = oy(c) = 0 and dox/du(c) + doy/dv(c) = 0 (central
    differences of 1 px). Apply as o' = Q o + t, d' = Q d, then slide o' to z = 0.
    """
    w, h = image_size
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    pts = c + np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], dtype=np.float64)
    o, d = rays(pts)
    e3 = d[0]
    du = (d[1] - d[2]) / 2
    e1 = du - (du @ e3) * e3
    e1 /= np.linalg.norm(e1)
    q = np.stack([e1, np.cross(e3, e1), e3])
    if central:
        return q, np.zeros(3)

    def slid(t: np.ndarray) -> np.ndarray:
        """Gauge residuals (3,) for translation t."""
        oo, dd = o @ q.T + t, d @ q.T
        oz = oo - (oo[:, 2] / dd[:, 2])[:, None] * dd
        return np.array([oz[0, 0], oz[0, 1], (oz[1, 0] - oz[2, 0]) / 2 + (oz[3, 1] - oz[4, 1]) / 2])

    base = slid(np.zeros(3))
    jac = np.stack([slid(e) - base for e in np.eye(3)], axis=1)
    return q, np.linalg.solve(jac, -base)


def in_gauge(rays: RayFn, q: np.ndarray, t: np.ndarray) -> RayFn:
    """Ray function of a camera moved by (Q, t), origins slid along the rays to z = 0."""

    def moved(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        o, d = rays(pixels)
        o, d = o @ q.T + t, d @ q.T
        return o - (o[:, 2] / d[:, 2])[:, None] * d, d

    return moved


# Truth sampled on this many points per image side to project it onto the spline mesh.
_PROJECTION_GRID = 160


def whitened_coefficient_errors(model: SGCCBase, rays: RayFn) -> np.ndarray:
    """Errors of a fitted sGCC model's control points against a true ray field, whitened by
    the fit's own covariance: N(0, 1) entries iff the predicted uncertainty is right.

    The truth is moved into the sGCC gauge and least-squares projected onto the model's mesh
    (its approximation error is not the fit's); the error is expressed in the eigenbasis of
    `model.covariance` without its gauge null space and divided by the predicted std of each
    eigen-direction. Unlike per-pixel z-scores, whose errors share a few weak modes, this has
    one independent entry per free parameter, so one fit's std(z) is sharp (about 1 +- 0.03).
    """
    if model.covariance is None:
        raise ValueError("whitened_coefficient_errors: the model carries no covariance")
    w, h = model.image_size
    central = model.n_components == 2
    q, t = sgcc_gauge_transform(rays, (w, h), central)
    uu, vv = np.meshgrid(np.linspace(-0.5, w - 0.5, _PROJECTION_GRID),
                         np.linspace(-0.5, h - 0.5, _PROJECTION_GRID))
    pix = np.stack([uu.ravel(), vv.ravel()], axis=1)
    o, d = in_gauge(rays, q, t)(pix)
    ok = np.all(np.isfinite(d), axis=1)
    values = logmap(d[ok]) if central else np.concatenate([logmap(d[ok]), o[ok, :2]], axis=1)
    truth = model.grid.fit(pix[ok, 0], pix[ok, 1], values, smooth=1e-14)
    n_gauge = len(gauge_constraints(model.grid, model.n_components, model.coeffs.size))
    lam, vec = np.linalg.eigh(model.covariance)  # ascending: the gauge directions come first
    lam, vec = lam[n_gauge:], vec[:, n_gauge:]
    return (vec.T @ (model.coeffs - truth).ravel()) / np.sqrt(lam)
