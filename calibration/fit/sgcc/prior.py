"""The sGCC prior centred on a parametric family, and the honest covariance of that fit.

A parametric camera model fitted to the same data is represented in the mesh by its
least-squares projection over the whole sensor, in the sGCC gauge (`FieldProjector`: the
same definition `calibration.compare` uses for a true ray field). The prior penalizes
every deviation of the spline from that field (second differences plus a ridge) except
along the family's tangent (`family_tangent`, how the field moves with each family
parameter): the family's parameters stay free and the data alone decide them, so the prior
neither claims the family fit's values nor counts its data twice (`deviation_precision`).
The estimate then follows the family's field in every other direction, and so inherits
that field's error there: the family fit's own uncertainty carried beyond its linear part
(the curvature of the field in the parameters, large for the near-degenerate rational
terms). `prior_covariance` is the data noise through the regularized normal equations
(A^-1 H A^-1) plus that term, sampled from the family's covariance.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
from scipy import sparse
from scipy.linalg import cho_factor, cho_solve, null_space

from calibration.fit.sgcc.initial import gauge_rotation
from calibration.fit.sgcc.lm import gauge_constraints
from calibration.fit.sgcc.state import LMResult
from calibration.models.bspline import SplineGrid, second_differences
from calibration.models.sgcc import logmap

_SAMPLES_PER_CELL = 16  # projection grid density (samples per cell along each axis)
_MIN_SAMPLES = 160
_PROJECTION_SMOOTH = 1e-14  # relative second-difference weight of the projection
_RIDGE = 1.0  # weight of the deviation itself next to its second differences
_TANGENT_STEP = 1e-2  # finite-difference step of the tangent, in parameter sigmas
NONLINEAR_SAMPLES = 16  # draws of the family's parameters for its curvature term


class FieldProjector:
    """Least-squares projection of a central model's ray field onto the mesh, over a dense
    grid of the whole sensor, rotated into the sGCC gauge (center ray +z, its u-derivative
    in the x-z plane), the gauge rows then made exact. Factorized once, reused per call."""

    def __init__(self, grid: SplineGrid, n_comp: int) -> None:
        w, h = grid.image_size
        nu = max(_MIN_SAMPLES, _SAMPLES_PER_CELL * grid.cells[0] + 1)
        nv = max(_MIN_SAMPLES, _SAMPLES_PER_CELL * grid.cells[1] + 1)
        uu, vv = np.meshgrid(np.linspace(-0.5, w - 0.5, nu), np.linspace(-0.5, h - 0.5, nv))
        self.grid, self.n_comp = grid, n_comp
        self.pixels = np.stack([uu.ravel(), vv.ravel()], axis=1)
        idx, wts = grid.basis(self.pixels[:, 0], self.pixels[:, 1])
        rows = np.repeat(np.arange(len(idx)), 16)
        self.design = sparse.csr_array((wts.ravel(), (rows, idx.ravel())),
                                       shape=(len(idx), grid.size))
        a = (self.design.T @ self.design).toarray()
        d = second_differences(grid)
        lam = _PROJECTION_SMOOTH * max(np.trace(a) / grid.size, 1e-12)
        self.factor = cho_factor(a + lam * (d.T @ d))
        self.cons = gauge_constraints(grid, n_comp, grid.size * n_comp)
        self.center = np.array([(w - 1) / 2, (h - 1) / 2])

    def __call__(self, model: Any) -> np.ndarray:
        """Flattened gauge-fixed coefficients (size * n_comp,) of `model`'s ray field."""
        d = model.unproject(self.center + np.array([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0]]))[1]
        q = gauge_rotation(d[0], (d[1] - d[2]) / 2)
        d = model.unproject(self.pixels)[1]
        ok = np.all(np.isfinite(d), axis=1)
        coeffs = np.zeros((self.grid.size, self.n_comp))
        if ok.all():
            coeffs[:, :2] = cho_solve(self.factor, self.design.T @ logmap(d @ q.T))
        else:  # beyond a fisheye's last valid angle: project what exists
            coeffs[:, :2] = self.grid.fit(self.pixels[ok, 0], self.pixels[ok, 1],
                                          logmap(d[ok] @ q.T), smooth=_PROJECTION_SMOOTH)
        x = coeffs.ravel()
        return x - self.cons.T @ np.linalg.solve(self.cons @ self.cons.T, self.cons @ x)


def _moved(model: Any, index: list[int], delta: np.ndarray) -> Any:
    """A copy of `model` with its parameters `index` moved by `delta`."""
    out = copy.deepcopy(model)
    p = model.get_params().copy()
    p[index] += delta
    out.set_params(p)
    return out


def family_tangent(model: Any, project: FieldProjector, sigmas: dict[str, float]
                   ) -> tuple[np.ndarray, list[int]]:
    """Columns (size * n_comp, k): derivative of the projected field along each parameter
    named in `sigmas` (central differences of `_TANGENT_STEP` sigmas), and their indices."""
    names = model.param_names()
    index = [names.index(n) for n in sigmas]
    cols = []
    for i, step in zip(index, (_TANGENT_STEP * s for s in sigmas.values()), strict=True):
        plus = project(_moved(model, [i], np.array([step])))
        minus = project(_moved(model, [i], np.array([-step])))
        cols.append((plus - minus) / (2.0 * step))
    return np.stack(cols, axis=1), index


def deviation_precision(grid: SplineGrid, n_comp: int, tangent: np.ndarray) -> np.ndarray:
    """B'(I - U U')B for B = [second differences; ridge] of the deviation from the family,
    U an orthonormal basis of B T (SVD): positive semi-definite by construction, zero along
    the family's tangent T, positive for every other deviation (curved or not)."""
    d = np.kron(second_differences(grid), np.eye(n_comp))
    b = np.vstack([d, np.sqrt(_RIDGE) * np.eye(d.shape[1])])
    u, s, _ = np.linalg.svd(b @ tangent, full_matrices=False)
    u = u[:, s > 1e-9 * s[0]] if s.size and s[0] > 0 else u[:, :0]
    br = b - u @ (u.T @ b)
    return br.T @ br


def prior_covariance(out: LMResult, grid: SplineGrid, n_comp: int, precision: np.ndarray,
                     model: Any, project: FieldProjector, tangent: np.ndarray,
                     index: list[int], rng: np.random.Generator, hold_last: bool = False
                     ) -> np.ndarray:
    """Full parameter covariance (spline then poses) of a fit with the family prior.

    Data noise: A^-1 H A^-1 (A = H + P, H the data's normal matrix, reduced to the gauge's
    null space z; times max(1, chi2/dof)). Family curvature: the family's parameters drawn
    from their covariance (from the same H with the poses free), the part of each projected
    field the tangent does not reach, mapped by the estimate's response A^-1 P to its centre.
    `hold_last`: the last parameter (a fitted screen's glass) was held, as run_lm does.
    """
    ns = grid.size * n_comp
    n = out.covariance.shape[0]
    rows = gauge_constraints(grid, n_comp, n)
    z = null_space(np.vstack([rows, np.eye(n)[-1]]) if hold_last else rows)
    scale = max(1.0, out.chi2_dof)
    a_inv = z.T @ out.covariance @ z / scale
    a_inv = 0.5 * (a_inv + a_inv.T)
    p_abs = out.prior_weight * precision
    h = np.linalg.inv(a_inv) - z[:ns].T @ p_abs @ z[:ns]
    k = tangent.shape[1]
    jt = np.zeros((n, k + n - ns))
    jt[:ns, :k] = tangent
    jt[ns:, k:] = np.eye(n - ns)
    jr = z.T @ jt
    sig = scale * np.linalg.pinv(jr.T @ h @ jr, hermitian=True)[:k, :k]
    lam, vec = np.linalg.eigh(0.5 * (sig + sig.T))
    root = vec * np.sqrt(np.clip(lam, 0.0, None))  # a square root even if barely definite
    base = project(model)
    draws = []
    for _ in range(NONLINEAR_SAMPLES):
        delta = root @ rng.standard_normal(k)
        draws.append(project(_moved(model, index, delta)) - base - tangent @ delta)
    resp = a_inv @ z[:ns].T @ p_abs @ np.array(draws).T  # (nz, samples)
    cz = scale * a_inv @ h @ a_inv + resp @ resp.T / NONLINEAR_SAMPLES
    cov = z @ cz @ z.T
    return 0.5 * (cov + cov.T)
