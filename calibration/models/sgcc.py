"""Smooth generic camera models (sGCC): ray fields as cubic B-splines over the sensor.

Direction: spline components (a, b) are the azimuthal-equidistant (exponential map)
coordinates of the unit ray about +z: r = (a sin(rho)/rho, b sin(rho)/rho, cos(rho)),
rho = |(a, b)|. This fixes the per-pixel scale of r, is smooth up to 180 degrees off
axis and is exactly linear in the pixel for an equidistant fisheye.
Origin (non-central only): o = (ox, oy, 0), spline components ox, oy in mm; o_z = 0
fixes the slide of o along r. Central models have o = 0.
"""

from __future__ import annotations

import base64
import binascii
from types import ModuleType
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from calibration.models.base import CameraModel, ModelError, register_model
from calibration.models.bspline import SplineGrid

DEFAULT_CELLS = (10, 10)
_PROJECT_ITERS = 30
_PROJECT_TOL_PX = 1e-9
_SEED_STEP_PX = 4.0
_COV_CHUNK = 2048


def expmap(ab: np.ndarray) -> np.ndarray:
    """Unit directions (N,3) from exponential-map coordinates (N,2) about +z."""
    rho = np.hypot(ab[:, 0], ab[:, 1])
    sinc = np.sinc(rho / np.pi)
    return np.stack([ab[:, 0] * sinc, ab[:, 1] * sinc, np.cos(rho)], axis=1)


def expmap_rows(a: Any, b: Any, xp: ModuleType = np) -> Any:
    """Directions as rows (3, N) from coordinate rows a, b (N,): the fit's feature-major layout.

    `xp` is the array module of a and b (NumPy or CuPy: the fit's device path).
    """
    rho = xp.sqrt(a * a + b * b)
    sinc = xp.sinc(rho / np.pi)
    return xp.stack([a * sinc, b * sinc, xp.cos(rho)])


def expmap_jacobian_rows(a: Any, b: Any, xp: ModuleType = np) -> tuple[Any, Any]:
    """Directions (3, N) and d r / d(a, b) (3, 2, N), feature-major (rows contiguous); `xp`
    is the array module of a and b (NumPy or CuPy). One sine and one cosine per point: the
    fit evaluates this on every pixel of every pass."""
    rho2 = a * a + b * b
    rho = xp.sqrt(rho2)
    small = rho < 1e-3
    inv = 1.0 / xp.where(small, 1.0, rho)
    cos = xp.cos(rho)
    sinc = xp.where(small, 1.0 - rho2 / 6.0, xp.sin(rho) * inv)
    # d(sinc)/d(rho) / rho = (cos - sinc) / rho^2, by its series where that cancels
    ds = xp.where(small, -1.0 / 3.0 + rho2 / 30.0, (cos - sinc) * (inv * inv))
    r = xp.empty((3, len(a)))
    r[0], r[1], r[2] = a * sinc, b * sinc, cos
    jac = xp.empty((3, 2, len(a)))
    jac[0, 0] = sinc + a * a * ds
    jac[0, 1] = a * b * ds
    jac[1, 0] = jac[0, 1]
    jac[1, 1] = sinc + b * b * ds
    jac[2, 0] = -r[0]
    jac[2, 1] = -r[1]
    return r, jac


def expmap_jacobian(ab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Directions (N,3) and d r / d(a, b) (N,3,2) of the exponential map."""
    r, jac = expmap_jacobian_rows(ab[:, 0], ab[:, 1])
    return r.T, jac.transpose(2, 0, 1)


def logmap(d: np.ndarray) -> np.ndarray:
    """Exponential-map coordinates (N,2) of directions (N,3) (any length)."""
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    rho = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
    s = np.hypot(d[:, 0], d[:, 1])
    scale = np.where(s > 1e-12, rho / np.where(s > 1e-12, s, 1.0), 1.0)
    return d[:, :2] * scale[:, None]


class SGCCBase(CameraModel):
    """Shared spline ray-field machinery; subclasses fix the number of components."""

    n_components: int = 2

    def __init__(
        self,
        image_size: tuple[int, int],
        cells: tuple[int, int] = DEFAULT_CELLS,
        coeffs: np.ndarray | None = None,
    ) -> None:
        super().__init__(image_size)
        self.grid = SplineGrid(self.image_size, (int(cells[0]), int(cells[1])))
        shape = (self.grid.size, self.n_components)
        if coeffs is None:
            coeffs = np.zeros(shape)
        coeffs = np.asarray(coeffs, dtype=np.float64)
        if coeffs.shape != shape:
            raise ModelError(f"coeffs: expected shape {list(shape)}, got {list(coeffs.shape)}")
        self.coeffs = coeffs
        self.covariance: np.ndarray | None = None  # (size*C, size*C), layout of get_params
        self._seeds: tuple[cKDTree, np.ndarray] | None = None

    def get_params(self) -> np.ndarray:
        """Control-point components, control-point major ((size, C) raveled)."""
        return self.coeffs.ravel().copy()

    def set_params(self, vector: np.ndarray) -> None:
        """Set all control-point components from a `get_params()` vector."""
        self.coeffs = np.asarray(vector, dtype=np.float64).reshape(self.coeffs.shape).copy()
        self._seeds = None

    def components(self, pixels: np.ndarray, derivatives: bool = False) -> tuple[np.ndarray, ...]:
        """Spline components (N, C) at pixels (N, 2) [+ d/du, d/dv]."""
        p = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        return self.grid.evaluate(self.coeffs, p[:, 0], p[:, 1], derivatives=derivatives)

    def _origins(self, comps: np.ndarray) -> np.ndarray:
        """Ray origins (N,3) mm from spline components."""
        o = np.zeros((len(comps), 3))
        if self.n_components == 4:
            o[:, :2] = comps[:, 2:4]
        return o

    def unproject(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closed form: spline components at the pixels -> (origins mm, unit directions)."""
        p = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        (comps,) = self.components(p)
        d = expmap(comps[:, :2])
        o = self._origins(comps)
        bad = ~np.all(np.isfinite(p), axis=1)
        d[bad] = np.nan
        o[bad] = np.nan
        return o, d

    def _seed_table(self) -> tuple[cKDTree, np.ndarray]:
        """KD-tree over (a, b) of a coarse pixel grid: starting points for `project`."""
        if self._seeds is None:
            w, h = self.image_size
            u = np.arange(-0.5, w - 0.5 + 1e-9, min(_SEED_STEP_PX, w / 8))
            v = np.arange(-0.5, h - 0.5 + 1e-9, min(_SEED_STEP_PX, h / 8))
            uu, vv = np.meshgrid(u, v)
            pix = np.stack([uu.ravel(), vv.ravel()], axis=1)
            (comps,) = self.components(pix)
            self._seeds = (cKDTree(comps[:, :2]), pix)
        return self._seeds

    def project(self, points: np.ndarray) -> np.ndarray:
        """3D points (N,3) mm -> pixels (N,2) by vectorized Newton on the spline; NaN if unseen.

        Target: exp-map coordinates of (p - o(u, v)); start: nearest coarse-grid seed; the
        origin's dependence on (u, v) is refreshed every step (it is tiny and smooth).
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points: expected shape (N, 3), got {p.shape}")
        tree, seeds = self._seed_table()
        finite = np.all(np.isfinite(p), axis=1)
        uv = np.full((len(p), 2), np.nan)
        if not finite.any():
            return uv
        target = logmap(p[finite])
        _, nearest = tree.query(target)
        uv[finite] = seeds[nearest]
        active = finite.copy()
        for _ in range(_PROJECT_ITERS):
            idx = np.nonzero(active)[0]
            if idx.size == 0:
                break
            comps, du, dv = self.components(uv[idx], derivatives=True)
            tgt = logmap(p[idx] - self._origins(comps))
            jac = np.stack([du[:, :2], dv[:, :2]], axis=2)
            det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
            ok = np.abs(det) > 1e-300
            step = np.zeros((idx.size, 2))
            step[ok] = np.linalg.solve(jac[ok], (tgt - comps[:, :2])[ok][..., None])[..., 0]
            w, h = self.image_size
            new = uv[idx] + step
            new[:, 0] = np.clip(new[:, 0], -0.5 - 2 * w, w - 0.5 + 2 * w)
            new[:, 1] = np.clip(new[:, 1], -0.5 - 2 * h, h - 0.5 + 2 * h)
            uv[idx] = new
            active[idx] = ok & (np.hypot(step[:, 0], step[:, 1]) > _PROJECT_TOL_PX)
        o, d = self.unproject(uv)
        w = p - o
        along = np.sum(w * d, axis=1)
        miss = np.linalg.norm(w - along[:, None] * d, axis=1)
        w_img, h_img = self.image_size
        inside = (
            (uv[:, 0] >= -0.5)
            & (uv[:, 0] <= w_img - 0.5)
            & (uv[:, 1] >= -0.5)
            & (uv[:, 1] <= h_img - 0.5)
        )
        good = finite & inside & (along > 0) & (miss <= 1e-6 * np.maximum(np.abs(along), 1.0))
        uv[~good] = np.nan
        return uv

    def ray_std(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel 1-sigma of the ray direction (rad) and origin (mm) from the covariance."""
        if self.covariance is None:
            raise ModelError("covariance: this model has no fitted covariance")
        cov = self.component_covariance(pixels)
        p = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        (comps,) = self.components(p)
        _, jac = expmap_jacobian(comps[:, :2])
        cdir = jac @ cov[:, :2, :2] @ np.transpose(jac, (0, 2, 1))
        ang = np.sqrt(np.maximum(np.trace(cdir, axis1=1, axis2=2), 0.0))
        org = (
            np.sqrt(np.maximum(np.trace(cov[:, 2:, 2:], axis1=1, axis2=2), 0.0))
            if self.n_components == 4
            else np.zeros(len(p))
        )
        return ang, org

    def direction_jacobian(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                              np.ndarray]:
        """The derivative of each pixel's unit ray direction over the coefficients, sparse:
        (exp-map Jacobian (N, 3, 2), control indices (N, 16), basis weights (N, 16)); the
        column of coefficient `idx * C + a` (a = 0, 1) is `jac[:, :, a] * weight` at the
        pixel's 16 controls and zero elsewhere (a dense one is pixels x coefficients)."""
        p = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        (comps,) = self.components(p)
        _, jac = expmap_jacobian(comps[:, :2])
        idx, w = self.grid.basis(p[:, 0], p[:, 1])
        return jac, idx, w

    def component_covariance(self, pixels: np.ndarray) -> np.ndarray:
        """Covariance (N, C, C) of the spline components at pixels, from the coefficients'."""
        if self.covariance is None:
            raise ModelError("covariance: this model has no fitted covariance")
        p = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        c = self.n_components
        out = np.empty((len(p), c, c))
        for start in range(0, len(p), _COV_CHUNK):
            q = p[start : start + _COV_CHUNK]
            idx, w = self.grid.basis(q[:, 0], q[:, 1])
            full = (idx[:, :, None] * c + np.arange(c)).reshape(len(q), -1)  # (n, 16C)
            sub = self.covariance[full[:, :, None], full[:, None, :]]
            sub = sub.reshape(len(q), 16, c, 16, c)
            out[start : start + _COV_CHUNK] = np.einsum("ni,nj,niajb->nab", w, w, sub)
        return out

    def params_to_json(self) -> dict[str, Any]:
        """Mesh cells and control points ([nv][nu][C] nested lists)."""
        nu, nv = self.grid.n_ctrl
        out: dict[str, Any] = {
            "cells": list(self.grid.cells),
            "components": ["a", "b", "ox_mm", "oy_mm"][: self.n_components],
            "control_points": self.coeffs.reshape(nv, nu, self.n_components).tolist(),
        }
        if self.covariance is not None:
            out["covariance_diag"] = np.diag(self.covariance).tolist()
            out["covariance_upper_f64_b64"] = _pack_upper(self.covariance)
        return out

    @classmethod
    def from_params_json(cls, image_size: tuple[int, int], params: dict[str, Any]) -> CameraModel:
        """Rebuild from `params_to_json()` output."""
        cells = params.get("cells")
        if (
            not isinstance(cells, list)
            or len(cells) != 2
            or not all(isinstance(c, int) and c >= 1 for c in cells)
        ):
            raise ModelError(f"params.cells: expected [cu, cv] positive integers, got {cells!r}")
        cp = np.asarray(params.get("control_points"), dtype=np.float64)
        expected = (cells[1] + 3, cells[0] + 3, cls.n_components)
        if cp.shape != expected:
            raise ModelError(
                f"params.control_points: expected shape {list(expected)}, got {list(cp.shape)}"
            )
        model = cls(image_size, (cells[0], cells[1]), cp.reshape(-1, cls.n_components))
        packed = params.get("covariance_upper_f64_b64")
        if packed is not None:
            model.covariance = _unpack_upper(packed, model.coeffs.size)
        return model


def _pack_upper(cov: np.ndarray) -> str:
    """Upper triangle (row-major, diagonal included) as base64 little-endian float64."""
    return base64.b64encode(cov[np.triu_indices(len(cov))].astype("<f8").tobytes()).decode()


def _unpack_upper(packed: Any, n: int) -> np.ndarray:
    """Inverse of `_pack_upper` for an (n, n) covariance; ModelError naming the field."""
    where = "params.covariance_upper_f64_b64"
    try:
        raw = base64.b64decode(packed, validate=True)
    except (TypeError, ValueError, binascii.Error) as exc:
        raise ModelError(f"{where}: expected base64 text ({exc})") from None
    count = n * (n + 1) // 2
    if len(raw) != 8 * count:
        raise ModelError(f"{where}: expected {count} float64 values for {n} parameters, "
                         f"got {len(raw) / 8:g}")
    upper = np.frombuffer(raw, dtype="<f8")
    if not np.all(np.isfinite(upper)):
        raise ModelError(f"{where}: contains non-finite values")
    cov = np.zeros((n, n))
    cov[np.triu_indices(n)] = upper
    return cov + np.triu(cov, 1).T


@register_model
class SGCCModel(SGCCBase):
    """Central smooth generic camera: direction spline (a, b), all origins at 0."""

    type_name = "sgcc"
    is_central = True
    n_components = 2


@register_model
class SGCCNonCentralModel(SGCCBase):
    """Non-central smooth generic camera: direction (a, b) and origin (ox, oy, 0) splines."""

    type_name = "sgcc-noncentral"
    is_central = False
    n_components = 4
