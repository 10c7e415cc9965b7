"""Uniform tensor-product cubic B-splines over the sensor: basis weights, derivatives, evaluation.

The spline of a sensor of W x H pixels spans [-0.5, W-0.5] x [-0.5, H-0.5] with
`cells = (cu, cv)` uniform cells and (cu+3) x (cv+3) control points; a point in cell
(i, j) is influenced by control points i..i+3 (u) and j..j+3 (v). Points outside the
sensor use the polynomial of the nearest edge cell (smooth extrapolation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

from calibration.models.blas_threads import single_thread_blas


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
        """Values (N, C) of spline components `coeffs` (size, C) [+ d/du, d/dv (N, C)].

        Pixels are grouped by cell; each cell's bicubic polynomial is applied separably
        (s first, then t), without a per-pixel gather of the 16 control points.
        """
        u, v = np.asarray(u, dtype=np.float64).ravel(), np.asarray(v, dtype=np.float64).ravel()
        with single_thread_blas():
            box = _lattice_box(u, v)
            if box is not None:
                return self._evaluate_lattice(coeffs, u, v, box, derivatives)
            return self._evaluate(coeffs, u, v, derivatives)

    def _axis_matrix(self, x: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
        """Dense basis (len(x), n_ctrl) and d/dpixel basis of the positions x along one axis."""
        cell, w, dw = self._axis(x, axis)
        m, dm = (np.zeros((len(x), self.n_ctrl[axis])) for _ in range(2))
        rows, cols = np.arange(len(x))[:, None], cell[:, None] + np.arange(4)
        m[rows, cols], dm[rows, cols] = w, dw
        return m, dm

    def _evaluate_lattice(
        self, coeffs: np.ndarray, u: np.ndarray, v: np.ndarray, box: tuple[int, int, int, int],
        derivatives: bool,
    ) -> tuple[np.ndarray, ...]:
        """`evaluate` at integer pixels filling much of their bounding box (decoded maps):
        the tensor-product spline on the whole box as two small matrix products per
        component (Bv P Bu^T), then gathered; far cheaper than per-pixel evaluation."""
        u0, v0, wb, hb = box
        bu, dbu = self._axis_matrix(np.arange(u0, u0 + wb, dtype=np.float64), 0)
        bv, dbv = self._axis_matrix(np.arange(v0, v0 + hb, dtype=np.float64), 1)
        flat = (v.astype(np.int64) - v0) * wb + (u.astype(np.int64) - u0)
        n_c = coeffs.shape[1]
        outs = [np.empty((len(u), n_c)) for _ in range(3 if derivatives else 1)]
        grid = coeffs.reshape(self.n_ctrl[1], self.n_ctrl[0], n_c)
        for c in range(n_c):
            rows = bv @ grid[:, :, c]  # (hb, nu): the spline along v, control columns in u
            outs[0][:, c] = (rows @ bu.T).ravel()[flat]
            if derivatives:
                outs[1][:, c] = (rows @ dbu.T).ravel()[flat]
                outs[2][:, c] = ((dbv @ grid[:, :, c]) @ bu.T).ravel()[flat]
        return tuple(outs)

    def _evaluate(
        self, coeffs: np.ndarray, u: np.ndarray, v: np.ndarray, derivatives: bool
    ) -> tuple[np.ndarray, ...]:
        """Body of `evaluate`."""
        cell, s, t = self.local(u, v)
        order = np.argsort(radix_keys(cell), kind="stable")
        cell, s, t = cell[order], s[order], t[order]
        n_c = coeffs.shape[1]
        # poly[cell, c, l, k]: coefficient of t^l s^k
        poly = np.einsum("ka,nkc->nca", monomial_basis(), coeffs[self.cell_controls()])
        poly = poly.reshape(-1, n_c * 4, 4)
        k = np.arange(1.0, 4.0)[:, None]
        outs = [np.empty((n_c, len(cell))) for _ in range(3 if derivatives else 1)]
        starts = np.flatnonzero(np.diff(cell, prepend=-1))
        ends = np.append(starts[1:], len(cell)) if starts.size else starts
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
            ps, pt = _powers(s[a:b], 3), _powers(t[a:b], 3)
            in_s = (poly[cell[a]] @ ps).reshape(n_c, 4, -1)  # sum over k, per (c, l)
            outs[0][:, a:b] = np.einsum("cln,ln->cn", in_s, pt)
            if derivatives:
                d_s = (poly[cell[a]][:, 1:] @ (k * ps[:-1])).reshape(n_c, 4, -1)
                outs[1][:, a:b] = np.einsum("cln,ln->cn", d_s, pt) / self.cell_px[0]
                outs[2][:, a:b] = (
                    np.einsum("cln,ln->cn", in_s[:, 1:], k * pt[:-1]) / self.cell_px[1]
                )
        inverse = np.empty_like(order)
        inverse[order] = np.arange(len(order))
        return tuple(np.ascontiguousarray(out[:, inverse].T) for out in outs)

    def fit(
        self, u: np.ndarray, v: np.ndarray, values: np.ndarray, smooth: float = 1e-6
    ) -> np.ndarray:
        """Least-squares control points (size, C) reproducing `values` (N, C) at (u, v).

        A small second-difference penalty (`smooth`, relative) keeps control points without
        data defined (they follow their neighbours smoothly).
        """
        idx, w = self.basis(u, v)
        n = self.size
        rows = np.repeat(np.arange(len(idx)), 16)
        design = sparse.csr_array((w.ravel(), (rows, idx.ravel())), shape=(len(idx), n))
        a = (design.T @ design).toarray()
        rhs = design.T @ values
        d = second_differences(self)
        lam = smooth * max(np.trace(a) / n, 1e-12)
        return np.linalg.solve(a + lam * (d.T @ d), rhs)


def _lattice_box(u: np.ndarray, v: np.ndarray) -> tuple[int, int, int, int] | None:
    """(u0, v0, width, height) of integer pixels that fill >= 1/4 of their bounding box
    (>= 4096 of them), where a separable evaluation on the box pays; else None."""
    if u.size < 4096 or not np.isfinite(u.sum() + v.sum()):
        return None
    if not (np.array_equal(np.floor(u), u) and np.array_equal(np.floor(v), v)):
        return None
    u0, v0 = int(u.min()), int(v.min())
    wb, hb = int(u.max()) - u0 + 1, int(v.max()) - v0 + 1
    return (u0, v0, wb, hb) if wb * hb <= 4 * u.size else None


def radix_keys(keys: np.ndarray) -> np.ndarray:
    """Keys as uint16 when they fit: numpy's stable argsort is then a radix sort."""
    return keys.astype(np.uint16) if keys.size and keys.max() < 2**16 else keys


def monomial_basis() -> np.ndarray:
    """Matrix K (16,16): the 16 basis weights of a cell are K @ (t^l s^k)[l*4+k], l, k < 4.

    Why: in this form the products of weights become moments of monomials, which is how
    the sGCC normal equations are accumulated (see calibration/fit/sgcc/problem.py).
    """
    t = np.linspace(0.0, 1.0, 4)
    w, _ = _basis_1d(t)  # (4 points, 4 weights)
    b = np.linalg.solve(np.vander(t, 4, increasing=True), w).T  # w_i(t) = sum_k b[i,k] t^k
    return np.kron(b, b)


def monomials(s: np.ndarray, t: np.ndarray, degree: int) -> np.ndarray:
    """Features as rows ((degree+1)^2, N): t^l s^k at row l*(degree+1)+k, for l, k <= degree."""
    ps, pt = _powers(s, degree), _powers(t, degree)
    return (pt[:, None, :] * ps[None, :, :]).reshape(-1, len(s))


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
