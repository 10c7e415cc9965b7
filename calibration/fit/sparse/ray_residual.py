"""Pixel residuals of an sGCC model at observed pixels, in closed form, with derivatives.

The sGCC model maps a pixel q to exponential-map coordinates ab(q) of its ray (and, if
non-central, an origin o(q)); projecting a point needs a Newton search over the spline.
For a point P seen at pixel q the fit instead takes one Newton step from q: the angular
miss e = logmap(P - o(q)) - ab(q) (rad, about +z) turned into pixels by the inverse of the
spline's local Jacobian M = d ab / d(u, v) (rad/px):

    r = M(q)^-1 e        (px: the projection of P minus q, to first order in r)

It is the pixel residual wherever residuals are small (sub-pixel corners: the neglected
term is of order |r|^2 times the spline's curvature over M), needs no inner iteration, is
defined for points whose projection would leave the sensor, and its derivatives are exact:
d r = M^-1 (d e - d M r), so a control point's weight at q enters as w + r_u w_u + r_v w_v,
the basis at the projected pixel to first order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.models.sgcc import SGCCBase, expmap_jacobian, logmap


@dataclass
class RayResidual:
    """Residuals of N points (px) and their derivatives (rows: u, v per point)."""

    pixels: np.ndarray  # (N, 2) model's pixel of the point minus the observed pixel
    d_coeffs: np.ndarray  # (N, 2, size*C) over `model.get_params()`
    d_point: np.ndarray  # (N, 2, 3) over the point in the camera frame (mm)


def logmap_jacobian(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exponential-map coordinates (N, 2) of vectors (N, 3) and their derivative (N, 2, 3)."""
    ab = logmap(v)
    _, je = expmap_jacobian(ab)  # (N, 3, 2), columns tangent to the sphere
    jt = np.transpose(je, (0, 2, 1))
    lj = np.linalg.solve(jt @ je, jt) / np.linalg.norm(v, axis=1)[:, None, None]
    return ab, lj


@dataclass
class PixelRays:
    """The spline at N pixels as the residual takes it: each pixel's ray (exponential-map
    coordinates and origin) and the inverse of the spline's local Jacobian there. A fit that
    holds the spline computes them once and only moves the points."""

    ab: np.ndarray  # (N, 2) rad
    origin: np.ndarray  # (N, 3) mm
    minv: np.ndarray  # (N, 2, 2) M^-1, px/rad

    def residual_pixels(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) residuals (px) of camera-frame `points` (N, 3) mm at these pixels."""
        return (self.minv @ (logmap(points - self.origin) - self.ab)[:, :, None])[:, :, 0]

    def subset(self, keep: np.ndarray) -> PixelRays:
        """The pixels selected by a boolean mask."""
        return PixelRays(self.ab[keep], self.origin[keep], self.minv[keep])


@dataclass
class _Miss:
    """The pieces of the residual at N pixels that its derivatives reuse."""

    basis: tuple[np.ndarray, ...]  # (idx, w, wdu, wdv) of the pixels
    minv: np.ndarray  # (N, 2, 2) M^-1, px/rad
    lj: np.ndarray | None  # (N, 2, 3) d logmap / d (point - origin), where asked for
    pixels: np.ndarray  # (N, 2) r


def _inverse_2x2(m: np.ndarray) -> np.ndarray:
    """(N, 2, 2) inverses in closed form (a batched LAPACK inverse costs several times more
    for 2x2 matrices, and the rig fit evaluates residuals for every Jacobian column)."""
    det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
    out = np.empty_like(m)
    out[:, 0, 0], out[:, 1, 1] = m[:, 1, 1], m[:, 0, 0]
    out[:, 0, 1], out[:, 1, 0] = -m[:, 0, 1], -m[:, 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return out / det[:, None, None]


def pixel_rays(model: SGCCBase, pixels: np.ndarray,
               basis: tuple[np.ndarray, ...] | None = None) -> PixelRays:
    """The model's rays and inverse local Jacobians at `pixels` (N, 2); `basis` is
    `model.grid.basis(u, v, derivatives=True)` at the pixels when cached."""
    q = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    basis = basis if basis is not None else model.grid.basis(q[:, 0], q[:, 1],
                                                             derivatives=True)
    idx, w, wdu, wdv = basis
    ctrl = model.coeffs[idx]  # (N, 16, C)
    # Batched (1 x 16) @ (16 x C) products: matmul takes a third of einsum's time here.
    comps = np.matmul(w[:, None, :], ctrl)[:, 0]
    jac_uv = np.matmul(ctrl[:, :, :2].transpose(0, 2, 1),
                       np.stack([wdu, wdv], axis=2))  # M (N, 2, 2): d ab / d (u, v)
    origin = np.zeros((len(q), 3))
    if model.n_components == 4:
        origin[:, :2] = comps[:, 2:4]
    return PixelRays(comps[:, :2], origin, _inverse_2x2(jac_uv))


def _miss(model: SGCCBase, pixels: np.ndarray, points: np.ndarray,
          basis: tuple[np.ndarray, ...] | None, derivatives: bool = True) -> _Miss:
    """r = M(q)^-1 (logmap(P - o(q)) - ab(q)) with what its derivatives need (the logmap's
    Jacobian only if `derivatives`)."""
    q = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    basis = basis if basis is not None else model.grid.basis(q[:, 0], q[:, 1],
                                                             derivatives=True)
    rays = pixel_rays(model, q, basis)
    if not derivatives:
        return _Miss(basis, rays.minv, None, rays.residual_pixels(points))
    target, lj = logmap_jacobian(points - rays.origin)
    return _Miss(basis, rays.minv, lj,
                 (rays.minv @ (target - rays.ab)[:, :, None])[:, :, 0])


def residual_pixels(model: SGCCBase, pixels: np.ndarray, points: np.ndarray,
                    basis: tuple[np.ndarray, ...] | None = None) -> np.ndarray:
    """(N, 2) residuals (px) of camera-frame `points` observed at `pixels`, without the
    derivatives (for fits that difference them numerically)."""
    return _miss(model, pixels, points, basis, derivatives=False).pixels


def ray_residual(model: SGCCBase, pixels: np.ndarray, points: np.ndarray,
                 basis: tuple[np.ndarray, ...] | None = None) -> RayResidual:
    """Residuals of camera-frame `points` (N, 3) mm observed at `pixels` (N, 2);
    `basis` is `model.grid.basis(u, v, derivatives=True)` at the pixels when cached."""
    m = _miss(model, pixels, points, basis)
    assert m.lj is not None
    idx, w, wdu, wdv = m.basis
    r, minv, c = m.pixels, m.minv, model.n_components
    n = len(r)
    d_coeffs = np.zeros((n, 2, model.coeffs.size))
    rows = np.arange(n)[:, None]
    moved = w + r[:, :1] * wdu + r[:, 1:] * wdv  # (N, 16)
    for comp in range(2):
        d_coeffs[rows, :, idx * c + comp] = -minv[:, None, :, comp] * moved[:, :, None]
    for comp in range(2, c):  # origin components move the target direction
        d_dir = -np.einsum("nij,nj->ni", minv, m.lj[:, :, comp - 2])
        d_coeffs[rows, :, idx * c + comp] = d_dir[:, None, :] * w[:, :, None]
    return RayResidual(r, d_coeffs, minv @ m.lj)
