"""Ray directions of the parametric models and their exact derivatives w.r.t. the intrinsics.

Pinhole family (opencv5, opencv-rational): the undistorted normalized point x_u solves
D(x_u; k) = ((u - cx)/fx, (v - cy)/fy); D's derivatives come from complex-step
differentiation of the model's own `distort` (exact to rounding, any distortion formula
built of arithmetic), x_u's by the implicit function theorem. Fisheye: theta solves
theta_d(theta; k) = |(a, b)|, differentiated likewise in closed form.
"""

from __future__ import annotations

import copy

import numpy as np

from calibration.models.parametric import FisheyeModel, PinholeFamily
from calibration.threads import map_in_threads

_NEWTON_ITERS = 30
_NEWTON_TOL = 1e-13
_CSTEP = 1e-30
_CHUNK = 1 << 15  # pixels per chunk of `directions`


def _distort_complex(model: PinholeFamily, x: np.ndarray, y: np.ndarray,
                     dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The model's distortion with complex inputs and coefficients (complex step); NaN
    where an input is not finite (a pixel `_undistort` did not converge on), without
    complex arithmetic on it (NumPy's complex division of a NaN warns "invalid value")."""
    finite = np.isfinite(x) & np.isfinite(y)
    saved = model.dist
    model.dist = dist
    try:
        if finite.all():
            return model.distort(x, y)
        dx, dy = (np.full(x.shape, complex(np.nan, np.nan)) for _ in range(2))
        dx[finite], dy[finite] = model.distort(x[finite], y[finite])
        return dx, dy
    finally:
        model.dist = saved


def _distort_jac_xy(model: PinholeFamily, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(N, 2, 2) dD/d(x, y) by complex step."""
    jac = np.empty((x.size, 2, 2))
    dist = model.dist.astype(np.complex128)
    for col, (ex, ey) in enumerate(((1j * _CSTEP, 0), (0, 1j * _CSTEP))):
        dx, dy = _distort_complex(model, x + ex, y + ey, dist)
        jac[:, 0, col], jac[:, 1, col] = dx.imag / _CSTEP, dy.imag / _CSTEP
    return jac


def solve2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve N 2x2 systems a x = b (b (N,2) or (N,2,K)) by the explicit inverse (fast)."""
    det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.stack([np.stack([a[:, 1, 1], -a[:, 0, 1]], 1),
                        np.stack([-a[:, 1, 0], a[:, 0, 0]], 1)], 1) / det[:, None, None]
    if b.ndim == 2:
        return inv[:, :, 0] * b[:, :1] + inv[:, :, 1] * b[:, 1:]
    return inv[:, :, 0, None] * b[:, None, 0, :] + inv[:, :, 1, None] * b[:, None, 1, :]


def _undistort(model: PinholeFamily, xd: np.ndarray, yd: np.ndarray,
               start: np.ndarray | None) -> np.ndarray:
    """(N, 2) x_u with D(x_u) = x_d by Newton (analytic 2x2 Jacobian); NaN if not converged."""
    xu = np.stack([xd, yd], axis=1) if start is None else start.copy()
    bad_start = ~np.all(np.isfinite(xu), axis=1)
    xu[bad_start] = np.stack([xd, yd], axis=1)[bad_start]
    target = np.stack([xd, yd], axis=1)
    for _ in range(_NEWTON_ITERS):
        fx, fy = model.distort(xu[:, 0], xu[:, 1])
        err = np.stack([fx, fy], axis=1) - target
        step = solve2(_distort_jac_xy(model, xu[:, 0], xu[:, 1]), err)
        xu -= step
        if np.nanmax(np.abs(step), initial=0.0) < _NEWTON_TOL:
            break
    fx, fy = model.distort(xu[:, 0], xu[:, 1])
    ok = np.hypot(fx - xd, fy - yd) < 1e-10
    xu[~ok] = np.nan
    return xu


def pinhole_directions(model: PinholeFamily, pixels: np.ndarray, start: np.ndarray | None = None,
                       jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Directions (N,3) (z = 1), d(dir)/d(params) (N,3,P) in `get_params()` order, and x_u."""
    u, v = pixels[:, 0], pixels[:, 1]
    xd, yd = (u - model.cx) / model.fx, (v - model.cy) / model.fy
    xu = _undistort(model, xd, yd, start)
    dirs = np.column_stack([xu, np.ones(len(xu))])
    if not jacobian:
        return dirs, None, xu
    n, nk = len(xu), model.n_dist
    jx = _distort_jac_xy(model, xu[:, 0], xu[:, 1])
    rhs = np.zeros((n, 2, 4 + nk))
    rhs[:, 0, 0], rhs[:, 1, 1] = -xd / model.fx, -yd / model.fy
    rhs[:, 0, 2], rhs[:, 1, 3] = -1 / model.fx, -1 / model.fy
    xc, yc = xu[:, 0].astype(np.complex128), xu[:, 1].astype(np.complex128)
    for i in range(nk):
        dist = model.dist.astype(np.complex128)
        dist[i] += 1j * _CSTEP
        dx, dy = _distort_complex(model, xc, yc, dist)
        rhs[:, 0, 4 + i], rhs[:, 1, 4 + i] = -dx.imag / _CSTEP, -dy.imag / _CSTEP
    dxu = solve2(jx, rhs)  # (N, 2, P)
    jac = np.concatenate([dxu, np.zeros((n, 1, 4 + nk))], axis=1)
    return dirs, jac, xu


def fisheye_directions(model: FisheyeModel, pixels: np.ndarray, start: np.ndarray | None = None,
                       jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Unit directions (N,3), d(dir)/d(params) (N,3,8) and theta (N,1) of the fisheye model."""
    a = (pixels[:, 0] - model.cx) / model.fx
    b = (pixels[:, 1] - model.cy) / model.fy
    rho = np.maximum(np.hypot(a, b), 1e-300)
    k = model.dist
    powers = np.arange(4) * 2 + 3  # theta^3, ^5, ^7, ^9

    def theta_d(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t2 = t * t
        val = t * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
        der = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
        return val, der

    theta = rho.copy() if start is None else np.where(np.isfinite(start[:, 0]), start[:, 0], rho)
    for _ in range(_NEWTON_ITERS):
        val, der = theta_d(theta)
        step = (val - rho) / der
        theta = theta - step
        if np.nanmax(np.abs(step), initial=0.0) < _NEWTON_TOL:
            break
    val, der = theta_d(theta)
    bad = ~(np.abs(val - rho) < 1e-10) | (theta < 0) | (theta >= np.pi) | (der <= 0)
    theta[bad] = np.nan
    st, ct = np.sin(theta), np.cos(theta)
    s = st / rho
    dirs = np.column_stack([a * s, b * s, ct])
    if not jacobian:
        return dirs, None, theta[:, None]
    n = len(a)
    da = np.zeros((n, 8))
    db = np.zeros((n, 8))
    da[:, 0], da[:, 2] = -a / model.fx, -1 / model.fx
    db[:, 1], db[:, 3] = -b / model.fy, -1 / model.fy
    drho = (a[:, None] * da + b[:, None] * db) / rho[:, None]
    dtheta = drho / der[:, None]
    dtheta[:, 4:] -= theta[:, None] ** powers / der[:, None]
    ds = (ct / rho)[:, None] * dtheta - (st / rho**2)[:, None] * drho
    jac = np.stack([s[:, None] * da + a[:, None] * ds, s[:, None] * db + b[:, None] * ds,
                    -st[:, None] * dtheta], axis=1)
    return dirs, jac, theta[:, None]


def directions(model: PinholeFamily, pixels: np.ndarray, start: np.ndarray | None = None,
               jacobian: bool = True, out: tuple | None = None
               ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Directions, their intrinsic Jacobian and a warm start for the next call, any family:
    computed in chunks of pixels (their temporaries stay in cache) over threads (NumPy
    releases the GIL in its loops; a multi-megapixel fit spends most of its time here).
    `out`: a previous call's result for as many pixels, whose arrays are filled again (no
    fresh pages for the ~400 bytes per pixel of a Jacobian; `start` may be one of them)."""
    family = fisheye_directions if isinstance(model, FisheyeModel) else pinhole_directions
    n = len(pixels)
    if n <= _CHUNK:
        return family(model, pixels, start, jacobian)
    parts = [slice(a, min(a + _CHUNK, n)) for a in range(0, n, _CHUNK)]
    first = family(copy.copy(model), pixels[parts[0]],
                   None if start is None else start[parts[0]], jacobian)
    arrays = [_filled(prev, new, n) for prev, new in zip(out or (None,) * 3, first, strict=True)]

    def one(sl: slice) -> None:
        # a copy per chunk: the complex step sets the coefficients on the model it is given
        done = family(copy.copy(model), pixels[sl], None if start is None else start[sl],
                      jacobian)
        for arr, part in zip(arrays, done, strict=True):
            if arr is not None:
                arr[sl] = part

    for arr, part in zip(arrays, first, strict=True):
        if arr is not None:
            arr[parts[0]] = part
    map_in_threads(one, parts[1:])
    dirs, jac, warm = arrays
    return dirs, jac, warm


def _filled(prev: np.ndarray | None, part: np.ndarray | None, n: int) -> np.ndarray | None:
    """`prev` if it holds n rows shaped like `part`'s, else a new array (None for None)."""
    if part is None:
        return None
    if prev is not None and prev.shape == (n, *part.shape[1:]) and prev.dtype == part.dtype:
        return prev
    return np.empty((n, *part.shape[1:]), dtype=part.dtype)
