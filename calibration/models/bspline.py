"""Uniform tensor-product cubic B-splines over the sensor: basis weights, derivatives, evaluation.

The spline of a sensor of W x H pixels spans [-0.5, W-0.5] x [-0.5, H-0.5] with
`cells = (cu, cv)` uniform cells and (cu+3) x (cv+3) control points; a point in cell
(i, j) is influenced by control points i..i+3 (u) and j..j+3 (v). Points outside the
sensor use the polynomial of the nearest edge cell (smooth extrapolation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _basis_1d(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cubic B-spline weights (N, 4) and their derivatives d/dt at local coordinate t."""
    t2, t3 = t * t, t * t * t
    w = (
        np.stack([(1 - t) ** 3, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3], axis=-1)
        / 6.0
    )
    dw = np.stack([-3 * (1 - t) ** 2, 9 * t2 - 12 * t, -9 * t2 + 6 * t + 3, 3 * t2], axis=-1) / 6.0
    return w, dw


@dataclass(frozen=True)
class SplineGrid:
    """Geometry of a uniform cubic B-spline mesh over an image of `image_size` (W, H)."""

    image_size: tuple[int, int]
    cells: tuple[int, int]

    def __post_init__(self) -> None:
        if min(self.cells) < 1:
            raise ValueError(f"cells: expected >= 1 cell per axis, got {list(self.cells)}")

    @property
    def n_ctrl(self) -> tuple[int, int]:
        """Control points per axis (u, v)."""
        return self.cells[0] + 3, self.cells[1] + 3

    @property
    def size(self) -> int:
        """Total number of control points."""
        return self.n_ctrl[0] * self.n_ctrl[1]

    @property
    def cell_px(self) -> tuple[float, float]:
        """Cell width and height in pixels."""
        return self.image_size[0] / self.cells[0], self.image_size[1] / self.cells[1]

    def _axis(self, x: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cell index, weights (N,4) and d-weights/dpixel (N,4) along one axis."""
        cell, s = self._local_axis(x, axis)
        w, dw = _basis_1d(s)
        return cell, w, dw / self.cell_px[axis]

    def local(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Flat cell index (N,) and local cell coordinates s (along u), t (along v) of pixels."""
        iu, su = self._local_axis(np.asarray(u, dtype=np.float64).ravel(), 0)
        iv, tv = self._local_axis(np.asarray(v, dtype=np.float64).ravel(), 1)
        return iv * self.cells[0] + iu, su, tv

    def _local_axis(self, x: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
        """Cell index and local coordinate (0..1 inside the sensor) along one axis."""
        s = (x + 0.5) / self.cell_px[axis]
        cell = np.clip(np.floor(s), 0, self.cells[axis] - 1).astype(np.int64)
        return cell, s - cell

    def cell_controls(self) -> np.ndarray:
        """Control indices (n_cells, 16) of every cell, in the order `basis` uses."""
        iv, iu = np.divmod(np.arange(self.cells[0] * self.cells[1]), self.cells[0])
        offs = np.arange(4)
        nu = self.n_ctrl[0]
        return ((iv[:, None] + offs)[:, :, None] * nu + (iu[:, None] + offs)[:, None, :]).reshape(
            -1, 16
        )

    def cell_of(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Flat cell index (iv * cu + iu) of each point."""
        iu, _, _ = self._axis(np.asarray(u, dtype=np.float64), 0)
        iv, _, _ = self._axis(np.asarray(v, dtype=np.float64), 1)
        return iv * self.cells[0] + iu

    def basis(
        self, u: np.ndarray, v: np.ndarray, derivatives: bool = False
    ) -> tuple[np.ndarray, ...]:
        """Control indices (N,16) and weights (N,16) [+ d/du, d/dv weights] at pixels (u, v)."""
        iu, wu, dwu = self._axis(np.asarray(u, dtype=np.float64).ravel(), 0)
        iv, wv, dwv = self._axis(np.asarray(v, dtype=np.float64).ravel(), 1)
        nu = self.n_ctrl[0]
        offs = np.arange(4)
        idx = ((iv[:, None] + offs)[:, :, None] * nu + (iu[:, None] + offs)[:, None, :]).reshape(
            -1, 16
        )
        w = (wv[:, :, None] * wu[:, None, :]).reshape(-1, 16)
        if not derivatives:
            return idx, w
        wdu = (wv[:, :, None] * dwu[:, None, :]).reshape(-1, 16)
        wdv = (dwv[:, :, None] * wu[:, None, :]).reshape(-1, 16)
        return idx, w, wdu, wdv

    def evaluate(
        self, coeffs: np.ndarray, u: np.ndarray, v: np.ndarray, derivatives: bool = False
    ) -> tuple[np.ndarray, ...]:
        """Values (N, C) of spline components `coeffs` (size, C) [+ d/du, d/dv (N, C)]."""
        if derivatives:
            idx, w, wdu, wdv = self.basis(u, v, derivatives=True)
            c = coeffs[idx]
            return (
                np.einsum("nk,nkc->nc", w, c),
                np.einsum("nk,nkc->nc", wdu, c),
                np.einsum("nk,nkc->nc", wdv, c),
            )
        idx, w = self.basis(u, v)
        return (np.einsum("nk,nkc->nc", w, coeffs[idx]),)

    def fit(
        self, u: np.ndarray, v: np.ndarray, values: np.ndarray, smooth: float = 1e-6
    ) -> np.ndarray:
        """Least-squares control points (size, C) reproducing `values` (N, C) at (u, v).

        A small second-difference penalty (`smooth`, relative) keeps control points without
        data defined (they follow their neighbours smoothly).
        """
        idx, w = self.basis(u, v)
        n = self.size
        a = np.zeros((n, n))
        np.add.at(a, (idx[:, :, None], idx[:, None, :]), w[:, :, None] * w[:, None, :])
        rhs = np.zeros((n, values.shape[1]))
        np.add.at(rhs, idx, w[:, :, None] * values[:, None, :])
        d = second_differences(self)
        lam = smooth * max(np.trace(a) / n, 1e-12)
        return np.linalg.solve(a + lam * (d.T @ d), rhs)


def monomial_basis() -> np.ndarray:
    """Matrix K (16,16): the 16 basis weights of a cell are K @ (t^l s^k)[l*4+k], l, k < 4.

    Why: in this form the products of weights become moments of monomials, which is how
    the sGCC normal equations are accumulated (see calibration/fit/sgcc_lm.py).
    """
    t = np.linspace(0.0, 1.0, 4)
    w, _ = _basis_1d(t)  # (4 points, 4 weights)
    b = np.linalg.solve(np.vander(t, 4, increasing=True), w).T  # w_i(t) = sum_k b[i,k] t^k
    return np.kron(b, b)


def monomials(s: np.ndarray, t: np.ndarray, degree: int) -> np.ndarray:
    """Features (N, (degree+1)^2) t^l s^k at index l*(degree+1)+k, for l, k <= degree.

    Returned as a transposed view of a (features, N) array so that per-feature rows are
    contiguous (cheap to build, and BLAS reads either layout).
    """
    ps, pt = _powers(s, degree), _powers(t, degree)
    return (pt[:, None, :] * ps[None, :, :]).reshape(-1, len(s)).T


def _powers(x: np.ndarray, degree: int) -> np.ndarray:
    """Rows x^0 .. x^degree, shape (degree+1, N)."""
    out = np.empty((degree + 1, len(x)))
    out[0] = 1.0
    for k in range(1, degree + 1):
        np.multiply(out[k - 1], x, out=out[k])
    return out


def second_differences(grid: SplineGrid) -> np.ndarray:
    """Matrix (rows, size) of second differences of the control net along u and v."""
    nu, nv = grid.n_ctrl
    rows = []
    ids = np.arange(grid.size).reshape(nv, nu)
    for a, b, c in (
        (ids[:, :-2], ids[:, 1:-1], ids[:, 2:]),
        (ids[:-2, :], ids[1:-1, :], ids[2:, :]),
    ):
        a, b, c = a.ravel(), b.ravel(), c.ravel()
        m = np.zeros((a.size, grid.size))
        r = np.arange(a.size)
        m[r, a] = 1.0
        m[r, b] = -2.0
        m[r, c] = 1.0
        rows.append(m)
    return np.vstack(rows)
