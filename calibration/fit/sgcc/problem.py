"""The sGCC fit's per-pixel geometry on the CPU: pixels sorted by (pose, cell), residuals and
normal equations accumulated per (pose, cell) group from monomial moments (see `Problem`)."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

from calibration.fit.observations import PoseObs
from calibration.fit.sgcc.screen_terms import panel_ray_terms, rays_in_screen_frame
from calibration.fit.sgcc.state import LMState
from calibration.metrology.screen_trace import N_SCREEN, ScreenTrace
from calibration.models.bspline import (
    SplineGrid,
    monomial_basis,
    monomials,
    radix_keys,
)
from calibration.threads import thread_count

# IRLS weights (n,) of a block's residuals e (2,n) mm, ok mask (n,) and inverse sigmas (2,n)
Weights = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
_JP_DENSE = [0, 1, 2, 5]  # pose-Jacobian columns that are not constant 0/1
_CHUNK = 1 << 13  # pixels per vectorized block: temporaries stay in cache, few Python calls


@dataclass(frozen=True)
class Segments:
    """Runs of equal (pose, cell) in pixels sorted by (pose, cell): bounds, pose, cell (S,)."""

    start: np.ndarray
    end: np.ndarray
    pose: np.ndarray
    cell: np.ndarray


def _segments(pose: np.ndarray, cell: np.ndarray) -> Segments:
    """The (pose, cell) runs of sorted pixels."""
    change = np.flatnonzero((pose[1:] != pose[:-1]) | (cell[1:] != cell[:-1])) + 1
    start = np.r_[0, change]
    return Segments(start, np.r_[change, len(pose)], pose[start], cell[start])


def _sorted(grid: SplineGrid, obs: list[PoseObs]) -> tuple[np.ndarray, ...]:
    """Pixels of all poses sorted by (pose, cell): inverse permutation (N,), local cell
    coordinates s, t (N,), screen mm and sigma mm (2, N), cell (N,). Sorted per pose and
    gathered straight into feature-major rows (few full-size temporaries)."""
    n = sum(len(o.pixels) for o in obs)
    inverse, cells = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    s, t, screen, sigma = np.empty(n), np.empty(n), np.empty((2, n)), np.empty((2, n))
    a = 0
    for o in obs:
        b = a + len(o.pixels)
        cell, sj, tj = grid.local(o.pixels[:, 0], o.pixels[:, 1])
        order = np.argsort(radix_keys(cell), kind="stable")
        inverse[a + order] = np.arange(a, b)
        for src, dst in ((sj, s), (tj, t), (cell, cells), *(
                (o.screen_mm[:, k], screen[k]) for k in range(2)), *(
                (o.sigma_mm[:, k], sigma[k]) for k in range(2))):
            np.take(src, order, out=dst[a:b])
        a = b
    return inverse, s, t, screen, sigma, cells


@dataclass(frozen=True)
class _Chunk:
    """Sorted pixels [a, b) of one pose and its cell groups (start, end relative to a, cell)."""

    a: int
    b: int
    pose: int
    groups: list[tuple[int, int, int]]


def _chunks(seg: Segments) -> list[_Chunk]:
    """Split the sorted pixels into per-pose blocks of whole cell groups."""
    out: list[_Chunk] = []
    cur: list[tuple[int, int, int]] = []
    pose0 = 0
    for a0, b0, pose, cell in zip(
        seg.start.tolist(), seg.end.tolist(), seg.pose.tolist(), seg.cell.tolist(), strict=True
    ):
        pieces = -(-(b0 - a0) // _CHUNK)  # long groups in even pieces (moments add up)
        bounds = [a0 + (b0 - a0) * i // pieces for i in range(pieces + 1)]
        for a, b in itertools.pairwise(bounds):
            if cur and (pose != pose0 or b - cur[0][0] > _CHUNK):
                out.append(_Chunk(cur[0][0], cur[-1][1], pose0, _relative(cur)))
                cur = []
            if not cur:
                pose0 = pose
            cur.append((a, b, cell))
    if cur:
        out.append(_Chunk(cur[0][0], cur[-1][1], pose0, _relative(cur)))
    return out


def _relative(groups: list[tuple[int, int, int]]) -> list[tuple[int, int, int]]:
    """Group bounds relative to the first group's start."""
    a0 = groups[0][0]
    return [(a - a0, b - a0, c) for a, b, c in groups]


def _over_chunks(chunks: list[_Chunk], work: Callable[[Sequence[_Chunk]], object]) -> list:
    """`work` on the chunks dealt round-robin to one share per thread; the shares' results.

    The chunk loops are NumPy vector operations that release the GIL, so threads use
    every core (the fit's dominant cost on multi-million-point problems).
    """
    n = thread_count(len(chunks))
    shares = [chunks[k::n] for k in range(n)]
    if n == 1:
        return [work(shares[0])]
    with ThreadPoolExecutor(n) as pool:
        return list(pool.map(work, shares))


def ray_terms(
    xp: ModuleType, comps: Any, rc: Any, tc: Any, screen: Any, jacobian: bool,
    panel: tuple[ScreenTrace, np.ndarray] | None = None,
) -> tuple[Any, ...]:
    """Residuals (Q-S) mm (2,n) and ok mask of pixels of one pose with spline components
    comps (C,n) [+ G = dQ/dcomponents (2,C,n), J = dQ/d(pose[, screen]) (2,6[+4],n)];
    arrays of module xp. `panel` (tracer, parameters): the fitted screen, else z = 0."""
    if panel is not None:
        return panel_ray_terms(xp, comps, rc, tc, screen, jacobian, panel)
    c = len(comps)
    jr, r_s, o_s, ok, rz = rays_in_screen_frame(xp, comps, rc, tc, jacobian)
    lam = -o_s[2] / rz
    q = o_s[:2] + lam * r_s[:2]
    res = xp.where(ok, q - screen, 0.0)
    if not jacobian:
        return res, ok
    p = r_s[:2] / rz  # dQ/d(o_s) = [[1, 0, -px], [0, 1, -py]]
    prc = rc[:2, :, None] - p[:, None, :] * rc[2][None, :, None]  # (2,3,n): dQ/d(o_s) Rc
    g = xp.empty((2, c, len(lam)))
    g[:, :2] = lam * (prc[:, :, None, :] * jr[None]).sum(axis=1)
    if c == 4:
        g[:, 2:] = prc[:, :2]
    qx, qy = q
    px, py = p
    jp = xp.zeros((2, 6, len(lam)))  # d/d(omega) = -dQ/d(o_s) [X]x, d/dt = dQ/d(o_s)
    jp[0, 0], jp[0, 1], jp[0, 2] = -px * qy, px * qx, -qy
    jp[1, 0], jp[1, 1], jp[1, 2] = -py * qy, py * qx, qx
    jp[0, 3], jp[1, 4] = 1.0, 1.0
    jp[0, 5], jp[1, 5] = -px, -py
    return res, ok, g, jp


def pose_terms(xp: ModuleType, e: Any, jp: Any, ws: Any) -> tuple[Any, Any]:
    """A block's pose-pose normal matrix J^T W J (6,6) and gradient J^T W e (6,).

    xp.dot, not @: NumPy's dot releases the GIL for the chunk threads.
    """
    pw = jp * ws[:, None, :]
    hpp = xp.dot(pw[0], jp[0].T) + xp.dot(pw[1], jp[1].T)
    return hpp, xp.dot(pw[0], e[0]) + xp.dot(pw[1], e[1])


def spline_terms(
    xp: ModuleType, e: Any, g: Any, jp: Any, ws: Any, tri: tuple[Any, Any]
) -> tuple[Any, Any]:
    """Per-pixel factors of the spline normal equations: the upper triangle (nt,n) of
    g^T W g and xg ((k+1)C,n), [a, q]: (g^T W jp)[a, q] for the k = 6 (pose) or 10 (pose,
    screen) columns of jp, q = k: (g^T W e)[a]."""
    iu, ju = tri
    k = jp.shape[1]
    c, n = g.shape[1:]
    gw = g * ws[:, None, :]
    # Row by row into preallocated rows: broadcast (C, k, n) products run strided and were
    # several times slower than these contiguous vector operations.
    hp = xp.empty((len(iu), n))
    for m, (i, j) in enumerate(zip(iu.tolist(), ju.tolist(), strict=True)):
        xp.multiply(gw[0, i], g[0, j], out=hp[m])
        hp[m] += gw[1, i] * g[1, j]
    xg = xp.empty((c, k + 1, n))
    # bare plane: jp[:, 3] = (1, 0), jp[:, 4] = (0, 1)
    for q in _JP_DENSE if k == 6 else range(k):
        xp.multiply(gw[0], jp[0, q], out=xg[:, q])
        xg[:, q] += gw[1] * jp[1, q]
    if k == 6:
        xg[:, 3], xg[:, 4] = gw[0], gw[1]
    xg[:, k] = gw[0] * e[0] + gw[1] * e[1]
    return hp, xg.reshape((k + 1) * c, n)


class Problem:
    """Fixed per-fit geometry: pixels sorted by (pose, cell), local cell coordinates, blocks.

    Per-pixel arrays are feature-major ((k, N), rows contiguous) so every step is a
    plain vector operation. Inside a cell the 16 basis weights are K m(s, t) with m the
    16 monomials t^l s^k (`monomial_basis`), so sum_p (w w^T) h_p = K [sum_p m m^T h_p] K^T
    needs only the 49 moments sum_p t^L s^M h_p (L, M <= 6) per cell: one small matrix
    product per (pose, cell) group.
    """

    def __init__(
        self, grid: SplineGrid, n_comp: int, obs: list[PoseObs], panel: ScreenTrace | None = None
    ) -> None:
        self.grid, self.c, self.panel = grid, n_comp, panel
        self.n_spline = grid.size * n_comp
        self.n_pose = len(obs)
        self.n_screen = 0 if panel is None else N_SCREEN  # parameters after the poses
        self.k = 6 + self.n_screen  # per-pixel non-spline Jacobian columns (pose, screen)
        self.n = self.n_spline + 6 * self.n_pose + self.n_screen
        self.n_cells = grid.cells[0] * grid.cells[1]
        self.inverse, self.s, self.t, self.screen, sigma, cell = _sorted(grid, obs)
        self.inv_sigma = np.divide(1.0, sigma, out=sigma)  # in place: one full-size array less
        self.counts = np.array([len(o.pixels) for o in obs])
        self.segments = _segments(np.repeat(np.arange(self.n_pose), self.counts), cell)
        self.chunks = _chunks(self.segments)
        self.kmat = monomial_basis()
        self.controls = grid.cell_controls()
        self.cols = (self.controls[:, :, None] * n_comp + np.arange(n_comp)).reshape(
            self.n_cells, -1
        )
        d = np.arange(4)
        self.pair = (
            (d[:, None, None, None] + d[None, None, :, None]) * 7
            + (d[None, :, None, None] + d[None, None, None, :])
        ).reshape(16, 16)
        self.tri = np.triu_indices(n_comp)

    def unsort(self, values: np.ndarray) -> list[np.ndarray]:
        """Per-pose arrays (feature-major rows in, pixel-major out) in the callers' order."""
        if values.ndim == 1:
            out = values[self.inverse]
        else:  # row by row: 3x faster than gathering rows of the transposed view
            out = np.empty(values.shape[::-1], dtype=values.dtype)
            for k, row in enumerate(values):
                out[:, k] = row[self.inverse]
        return np.split(out, np.cumsum(self.counts)[:-1])

    def _chunk(
        self, st: LMState, poly: np.ndarray, ch: _Chunk, jacobian: bool
    ) -> tuple[np.ndarray, ...]:
        """Residuals (Q-S) mm (2,n) and ok mask of a block [+ monomials, G (2,C,n), J (2,k,n)]."""
        m16 = monomials(self.s[ch.a : ch.b], self.t[ch.a : ch.b], 3)
        comps = np.empty((self.c, ch.b - ch.a))
        for a, b, cell in ch.groups:
            np.matmul(poly[cell], m16[:, a:b], out=comps[:, a:b])
        screen = self.screen[:, ch.a : ch.b]
        out = ray_terms(np, comps, st.rc[ch.pose], st.tc[ch.pose], screen, jacobian,
                        self.panel_at(st))
        if not jacobian:
            return out
        res, ok, g, jp = out
        return res, ok, m16, g, jp

    def panel_at(self, st: LMState) -> tuple[ScreenTrace, np.ndarray] | None:
        """The fitted screen's tracer and parameters in state st (None: bare plane z = 0)."""
        if self.panel is None:
            return None
        if st.screen is None:
            raise ValueError("sgcc: a fitted screen needs LMState.screen parameters")
        return self.panel, st.screen

    def polynomials(self, coeffs: np.ndarray) -> np.ndarray:
        """Monomial coefficients (n_cells, C, 16) of every cell's spline components."""
        return np.einsum("ka,nkc->nca", self.kmat, coeffs[self.controls])

    def residuals(self, st: LMState) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (Q-S) mm (2,N) and ok mask (N,) of all pixels, sorted order."""
        n = len(self.s)
        res, ok = np.empty((2, n)), np.empty(n, dtype=bool)
        poly = self.polynomials(st.coeffs)

        def fill(share: Sequence[_Chunk]) -> None:
            """Write the residuals of a share of chunks (disjoint slices)."""
            for ch in share:
                res[:, ch.a : ch.b], ok[ch.a : ch.b] = self._chunk(st, poly, ch, jacobian=False)

        _over_chunks(self.chunks, fill)
        return res, ok

    def _moments(
        self, st: LMState, poly: np.ndarray, wt: np.ndarray, share: Sequence[_Chunk], spline: bool,
        hessian: bool = True, out: tuple[np.ndarray, np.ndarray, Weights] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Normal-equation sums of a share of chunks: per-cell moments, spline-pose cross
        moments, and the per-pose blocks (see `normal_equations`); without `hessian` only
        the gradient columns of the cross moments (the rest stays zero). `out` (res, ok,
        weights): each block's residuals and ok mask are written there and its weights
        wt computed from them (`residuals_and_normal_equations`)."""
        c, nc, npo, k = self.c, self.n_cells, self.n_pose, self.k
        mom = np.zeros((nc, 49, len(self.tri[0])))  # sum m49 * (g^T W g)[upper triangle]
        cross = np.zeros((npo, nc, 16, (k + 1) * c))  # sum m16 * xg (see `spline_terms`)
        hpp, gpp = np.zeros((npo, k, k)), np.zeros((npo, k))
        for ch in share:
            e, ok, m16, g, jp = self._chunk(st, poly, ch, jacobian=True)
            if out is not None:
                out[0][:, ch.a : ch.b], out[1][ch.a : ch.b] = e, ok
                wt[ch.a : ch.b] = out[2](e, ok, self.inv_sigma[:, ch.a : ch.b])
            ws = wt[ch.a : ch.b] * self.inv_sigma[:, ch.a : ch.b] ** 2  # (2,n)
            hpp_c, gpp_c = pose_terms(np, e, jp, ws)
            hpp[ch.pose] += hpp_c
            gpp[ch.pose] += gpp_c
            if not spline:
                continue
            if not hessian:  # g^T W e per component: the last of each component's columns
                ge = g[0] * (ws[0] * e[0]) + g[1] * (ws[1] * e[1])
                grad = cross.reshape(npo, nc, 16, c, -1)[..., -1]
                for a, b, cell in ch.groups:
                    grad[ch.pose, cell] += np.dot(m16[:, a:b], ge[:, a:b].T)
                continue
            hp, xg = spline_terms(np, e, g, jp, ws, self.tri)
            m49 = monomials(self.s[ch.a : ch.b], self.t[ch.a : ch.b], 6)
            for a, b, cell in ch.groups:  # np.dot, not @: it releases the GIL for threads
                mom[cell] += np.dot(m49[:, a:b], hp[:, a:b].T)
                cross[ch.pose, cell] += np.dot(m16[:, a:b], xg[:, a:b].T)
        return mom, cross, hpp, gpp

    def normal_equations(
        self, st: LMState, wt: np.ndarray, spline: bool = True, hessian: bool = True
    ) -> tuple[np.ndarray, np.ndarray]:
        """J^T W J and J^T W e from per-cell monomial moments (spline) and per-pose sums.
        `hessian=False`: J^T W e only (the spline blocks of J^T W J are then not valid), for
        less than half the work (LM's chord steps, sgcc/lm.py)."""
        poly = self.polynomials(st.coeffs)
        parts = _over_chunks(
            self.chunks, lambda share: self._moments(st, poly, wt, share, spline, hessian)
        )
        mom, cross, hpp, gpp = (sum(p[k] for p in parts) for k in range(4))
        return self.assemble(hpp, gpp, (mom, cross) if spline else None)

    def residuals_and_normal_equations(
        self, st: LMState, weights: Weights, spline: bool = True, hessian: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """`residuals` and, in the same pass, `normal_equations` (J^T W e alone unless
        `hessian`) with each block's weights from its residuals, `weights(e, ok, inv_sigma)`:
        one pass where LM needs both (sgcc/lm.py)."""
        n = len(self.s)
        res, ok, wt = np.empty((2, n)), np.empty(n, dtype=bool), np.empty(n)
        poly = self.polynomials(st.coeffs)
        parts = _over_chunks(self.chunks, lambda share: self._moments(
            st, poly, wt, share, spline, hessian, out=(res, ok, weights)))
        mom, cross, hpp, gpp = (sum(p[k] for p in parts) for k in range(4))
        return res, ok, *self.assemble(hpp, gpp, (mom, cross) if spline else None)

    def assemble(
        self, hpp: np.ndarray, gpp: np.ndarray, moments: tuple[np.ndarray, np.ndarray] | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """J^T W J and J^T W e from the per-pose sums (npo,k,k), (npo,k) and, unless the spline
        is fixed (None), the per-cell moments (nc,49,nt) and per-(pose, cell) cross moments
        (npo,nc,16,(k+1)C); with a fitted screen its 4 parameters come last."""
        c, ns, nc, npo, k = self.c, self.n_spline, self.n_cells, self.n_pose, self.k
        iu, ju = self.tri
        h, grad = np.zeros((self.n, self.n)), np.zeros(self.n)
        scr = slice(ns + 6 * npo, self.n)
        for j in range(npo):
            sl = slice(ns + 6 * j, ns + 6 * j + 6)
            h[sl, sl], grad[sl] = hpp[j][:6, :6], gpp[j][:6]
            if k > 6:
                h[sl, scr], h[scr, sl] = hpp[j][:6, 6:], hpp[j][6:, :6]
                h[scr, scr] += hpp[j][6:, 6:]
                grad[scr] += gpp[j][6:]
        if moments is None:
            return h, grad
        mom, cross = moments
        full = np.zeros((nc, 49, c, c))
        full[:, :, iu, ju] = mom
        full[:, :, ju, iu] = mom
        kk = self.kmat
        blk = np.einsum("ia,nabxy,jb->nixjy", kk, full[:, self.pair], kk, optimize=True)
        cols = self.cols
        np.add.at(h, (cols[:, :, None], cols[:, None, :]), blk.reshape(nc, 16 * c, 16 * c))
        xk = np.einsum("ia,pnaz->pniz", kk, cross)
        hsp = np.zeros((ns, 6 * npo + k - 6))
        for j in range(npo):
            blk_j = xk[j].reshape(nc, 16, c, k + 1)[..., :6].reshape(nc, 16 * c, 6)
            np.add.at(hsp, (cols[:, :, None], 6 * j + np.arange(6)), blk_j)
        xsum = xk.sum(axis=0).reshape(nc, 16, c, k + 1)
        if k > 6:  # spline-screen: summed over the poses
            np.add.at(hsp, (cols[:, :, None], 6 * npo + np.arange(k - 6)),
                      xsum[..., 6:k].reshape(nc, 16 * c, k - 6))
        h[:ns, ns:] = hsp
        h[ns:, :ns] = hsp.T
        np.add.at(grad, cols, xsum[..., k].reshape(nc, 16 * c))
        return h, grad
