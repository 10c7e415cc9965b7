"""sGCC residuals and normal equations on an array module (NumPy or CuPy): the GPU path.

`Problem` (sgcc/problem.py) loops in Python over (pose, cell) groups of a few thousand pixels:
right for threaded NumPy, but thousands of tiny kernel launches per iteration on a GPU.
Here each span of up to `_CHUNK` sorted pixels of one pose is a few whole-array operations.
Its monomials are the values of a sparse design matrix A (n, S k): row p holds the k
monomials of pixel p in the k columns of its (pose, cell) segment (S segments in the span),
so with no loop over segments
- the spline components are A16 @ P, P (S 16, C) the segments' cell polynomials;
- the moments sum_p m49 (g^T W g) and sum_p m16 xg of every segment are A49^T @ hp^T and
  A16^T @ xg^T: exact per-segment sums (no cumulative sums) as sparse-dense products
  (scipy.sparse / cupyx.scipy.sparse, cuSPARSE on the GPU).
The sorted per-pixel inputs stay on the device for the whole fit phase. Per call the host
sends the cell polynomials, the poses and (normal equations) the weights (N,), and gets back
the residuals (2,N) and ok mask, or the per-segment moments; the small dense assembly and
the solves stay on the host (`Problem.assemble`).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

from calibration.decode.arrays import to_host
from calibration.fit.sgcc.problem import Problem, Weights, pose_terms, ray_terms, spline_terms
from calibration.fit.sgcc.state import LMState

_CHUNK = 1 << 19  # pixels per span: about 2 KB of device temporaries each (moments)


@dataclass(frozen=True)
class _Span:
    """Sorted pixels [a, b) of one pose; they touch segments [s0, s1)."""

    a: int
    b: int
    pose: int
    s0: int
    s1: int


def _sparse(xp: ModuleType) -> ModuleType:
    """`cupyx.scipy.sparse` for CuPy, else `scipy.sparse` (the same csr_matrix interface)."""
    if getattr(xp, "__name__", "") == "cupy":
        return importlib.import_module("cupyx.scipy.sparse")
    return importlib.import_module("scipy.sparse")


def _powers(xp: ModuleType, x: Any, degree: int) -> Any:
    """Pixel-major powers (n, degree+1) of x, chained products as in `bspline.monomials`."""
    out = xp.empty((len(x), degree + 1))
    out[:, 0] = 1.0
    for k in range(1, degree + 1):
        out[:, k] = out[:, k - 1] * x
    return out


def _monomials(ps: Any, pt: Any, degree: int) -> Any:
    """Pixel-major monomials (n, (degree+1)^2): t^l s^k in column l*(degree+1)+k."""
    d = degree + 1
    return (pt[:, :d, None] * ps[:, None, :d]).reshape(len(ps), d * d)


class DeviceProblem:
    """`Problem`'s residuals and normal equations, same meaning and results, computed with
    array module `xp` (CuPy on a GPU; NumPy works too, single-threaded, for testing)."""

    def __init__(self, prob: Problem, xp: ModuleType, chunk: int = _CHUNK) -> None:
        self.prob, self.xp, self.sparse = prob, xp, _sparse(xp)
        self.n_spline, self.inv_sigma, self.unsort = prob.n_spline, prob.inv_sigma, prob.unsort
        seg = prob.segments
        seg_of = np.repeat(np.arange(len(seg.start), dtype=np.int32), seg.end - seg.start)
        self.dev_s, self.dev_t = xp.asarray(prob.s), xp.asarray(prob.t)
        self.dev_screen, self.dev_inv_sigma = xp.asarray(prob.screen), xp.asarray(prob.inv_sigma)
        self.dev_seg, self.dev_seg_cell = xp.asarray(seg_of), xp.asarray(seg.cell)
        self.dev_tri = (xp.asarray(prob.tri[0]), xp.asarray(prob.tri[1]))
        self.spans: list[_Span] = []
        start = 0
        for pose, count in enumerate(prob.counts.tolist()):
            for a in range(start, start + count, chunk):
                b = min(a + chunk, start + count)
                self.spans.append(_Span(a, b, pose, int(seg_of[a]), int(seg_of[b - 1]) + 1))
            start += count

    def _send(self, st: LMState) -> tuple[Any, list[tuple[Any, Any]]]:
        """Cell polynomials as rows (n_cells, 16, C) and per-pose (Rc, tc), on the device."""
        xp = self.xp
        poly = np.ascontiguousarray(self.prob.polynomials(st.coeffs).transpose(0, 2, 1))
        poses = [(xp.asarray(rc), xp.asarray(tc)) for rc, tc in zip(st.rc, st.tc, strict=True)]
        return xp.asarray(poly), poses

    def _design(self, values: Any, sp: _Span) -> Any:
        """Sparse (n, S k) matrix of a span: row p holds the k values of pixel p in the
        columns of its segment (sorted, unique: canonical CSR)."""
        xp = self.xp
        n, k = values.shape
        local = self.dev_seg[sp.a : sp.b] - sp.s0
        indices = (local[:, None] * k + xp.arange(k, dtype=local.dtype)).ravel()
        indptr = xp.arange(0, n * k + 1, k, dtype=local.dtype)
        mat = self.sparse.csr_matrix(
            (values.ravel(), indices, indptr), shape=(n, (sp.s1 - sp.s0) * k)
        )
        mat.has_canonical_format = True  # true by construction; spares the check
        return mat

    def _components(self, poly: Any, sp: _Span, degree: int) -> tuple[Any, Any, Any, Any]:
        """Spline components (C, n) of a span, its design matrix A16 and the powers (n,
        degree+1) of its local coordinates s and t."""
        s, t = self.dev_s[sp.a : sp.b], self.dev_t[sp.a : sp.b]
        ps, pt = _powers(self.xp, s, degree), _powers(self.xp, t, degree)
        a16 = self._design(_monomials(ps, pt, 3), sp)
        cells = poly[self.dev_seg_cell[sp.s0 : sp.s1]]  # (S, 16, C)
        comps = (a16 @ cells.reshape(-1, cells.shape[2])).T
        return comps, a16, ps, pt

    def residuals(self, st: LMState) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (Q-S) mm (2,N) and ok mask (N,) of all pixels, sorted order, on the host."""
        xp = self.xp
        n = len(self.prob.s)
        res, ok = xp.empty((2, n)), xp.empty(n, dtype=bool)
        poly, poses = self._send(st)
        for sp in self.spans:
            comps, _, _, _ = self._components(poly, sp, 3)
            rc, tc = poses[sp.pose]
            screen = self.dev_screen[:, sp.a : sp.b]
            res[:, sp.a : sp.b], ok[sp.a : sp.b] = ray_terms(xp, comps, rc, tc, screen, False,
                                                             self.prob.panel_at(st))
        return to_host(res), to_host(ok)

    def residuals_and_normal_equations(
        self, st: LMState, weights: Weights, spline: bool = True, hessian: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """`Problem.residuals_and_normal_equations` (host arrays) as a residual pass, then the
        normal equations with the weights of those residuals: the same numbers."""
        res, ok = self.residuals(st)
        h, grad = self.normal_equations(st, weights(res, ok, self.inv_sigma), spline, hessian)
        return res, ok, h, grad

    def normal_equations(
        self, st: LMState, wt: np.ndarray, spline: bool = True, hessian: bool = True
    ) -> tuple[np.ndarray, np.ndarray]:
        """J^T W J and J^T W e (host) as `Problem.normal_equations`, weights wt (N,) host
        (always both: `hessian=False` saves little on a device)."""
        xp, prob = self.xp, self.prob
        c, nt, n_seg, k = prob.c, len(prob.tri[0]), len(prob.segments.start), prob.k
        poly, poses = self._send(st)
        panel = prob.panel_at(st)
        dev_wt = xp.asarray(wt)
        hpp, gpp = xp.zeros((prob.n_pose, k, k)), xp.zeros((prob.n_pose, k))
        mom = xp.zeros((n_seg, 49, nt))  # per segment: sum m49 * (g^T W g)[upper triangle]
        cross = xp.zeros((n_seg, 16, (k + 1) * c))  # per segment: sum m16 * xg
        for sp in self.spans:
            comps, a16, ps, pt = self._components(poly, sp, 6 if spline else 3)
            rc, tc = poses[sp.pose]
            e, _, g, jp = ray_terms(xp, comps, rc, tc, self.dev_screen[:, sp.a : sp.b], True,
                                    panel)
            ws = dev_wt[sp.a : sp.b] * self.dev_inv_sigma[:, sp.a : sp.b] ** 2  # (2,n)
            hpp_c, gpp_c = pose_terms(xp, e, jp, ws)
            hpp[sp.pose] += hpp_c
            gpp[sp.pose] += gpp_c
            if not spline:
                continue
            hp, xg = spline_terms(xp, e, g, jp, ws, self.dev_tri)
            a49 = self._design(_monomials(ps, pt, 6), sp)
            mom[sp.s0 : sp.s1] += (a49.T @ hp.T).reshape(-1, 49, nt)
            cross[sp.s0 : sp.s1] += (a16.T @ xg.T).reshape(-1, 16, (k + 1) * c)
        if not spline:
            return prob.assemble(to_host(hpp), to_host(gpp), None)
        seg = prob.segments
        mom_cells = np.zeros((prob.n_cells, 49, nt))
        np.add.at(mom_cells, seg.cell, to_host(mom))
        cross_cells = np.zeros((prob.n_pose, prob.n_cells, 16, (k + 1) * c))
        cross_cells[seg.pose, seg.cell] = to_host(cross)  # one segment per (pose, cell)
        return prob.assemble(to_host(hpp), to_host(gpp), (mom_cells, cross_cells))
