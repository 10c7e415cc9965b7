"""Levenberg–Marquardt for sGCC ray-field splines and screen poses (PHYSICS.md section 5).

Residual of pixel p in pose j: the model ray, moved into the screen frame
(o_s = Rc o + tc, r_s = Rc r with Rc = R_j^T, tc = -R_j^T t_j), meets the plane z = 0 at
Q; e = (Q - S_p) / sigma_p (screen mm over screen mm: a Mahalanobis distance).
Normal equations: every residual touches the 16 control points of its cell and its pose's
6 parameters, so they are accumulated per (pose, cell) group from monomial moments with
small matrix products (see `_Problem`; no loop over pixels). Large fits converge on an
even subset first (`run_lm`). Robustness: Huber weights (k = 3) with a hard cut at
`cut` sigmas (redescending; pixels beyond it are treated as outliers).

Gauge (explicit, linear constraints kept exact by stepping in their null space):
- per pixel: r is unit by construction (exp-map coordinates), o_z = 0;
- rotation of the camera frame: a(c) = b(c) = 0 and db/du(c) = 0 at the sensor center c
  (the center ray is +z and its u-derivative lies in the x-z plane);
- translation (non-central only): ox(c) = oy(c) = 0 and dox/du(c) + doy/dv(c) = 0.
A weak second-difference prior (relative weight `smooth`) defines control points without
data; where data exist it is negligible, where they do not its large covariance shows it.
`LMOptions.xp = "cupy"` moves the per-pixel work to a GPU (`calibration/fit/sgcc_device.py`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.linalg import cho_factor, cho_solve, null_space
from scipy.spatial.transform import Rotation

from calibration.decode.arrays import array_module
from calibration.models.blas_threads import single_thread_blas
from calibration.models.bspline import (
    SplineGrid,
    monomial_basis,
    monomials,
    radix_keys,
    second_differences,
)
from calibration.models.sgcc import expmap_jacobian_rows, expmap_rows

if TYPE_CHECKING:
    from calibration.fit.sgcc_device import DeviceProblem


@dataclass
class PoseObs:
    """The decoded points of one pose: pixels (N,2), screen mm (N,2), sigma mm (N,2)."""

    pixels: np.ndarray
    screen_mm: np.ndarray
    sigma_mm: np.ndarray


@dataclass
class LMOptions:
    """Knobs of the LM loop (all have working defaults)."""

    max_iterations: int = 60
    huber_k: float = 3.0
    cut_sigmas: float = 8.0
    smooth: float = 1e-10
    rel_tol: float = 1e-10
    # Converged when the undamped Gauss-Newton step would lower the chi^2 by at most this
    # (times chi^2/dof where that exceeds 1, as the covariance is): the state is then within
    # sqrt(chi2_tol) joint standard deviations of the optimum, and the step taken from there
    # leaves only a second-order remainder.
    chi2_tol: float = 1.0
    fix_spline: bool = False
    subset_pixels: int = 100_000  # early iterations on about this many points (large fits)
    # Array module of the per-pixel work: "numpy" (threaded CPU) or "cupy" (GPU, sgcc_device).
    xp: str = "numpy"


@dataclass
class LMState:
    """Spline components (size, C) and camera->screen transforms of each pose."""

    coeffs: np.ndarray
    rc: list[np.ndarray]  # (3,3) each
    tc: list[np.ndarray]  # (3,) each


@dataclass
class LMResult:
    """Converged state plus what the statistics need."""

    state: LMState
    iterations: int
    converged: bool
    cost: float
    covariance: np.ndarray  # full parameter covariance (spline then poses)
    min_eig: float  # smallest eigenvalue of the Jacobi-scaled reduced normal equations
    residuals: list[np.ndarray]  # per pose (N,2) screen mm (Q - S)
    inliers: list[np.ndarray]  # per pose bool (N,)
    chi2_dof: float
    history: list[float] = field(default_factory=list)


_JP_DENSE = [0, 1, 2, 5]  # pose-Jacobian columns that are not constant 0/1
_CHUNK = 1 << 16  # pixels per vectorized block: bounded temporaries, few Python-level calls
_DAMPING_TRIES = 12  # LM damping increases per iteration before giving up
_GAUSS_NEWTON_BELOW = 1e-6  # Jacobi-scaled damping under which the undamped step goes first
_MAX_THREADS = 4  # chunk threads: NumPy releases the GIL in its loops; more only contend


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
    for a, b, pose, cell in zip(
        seg.start.tolist(), seg.end.tolist(), seg.pose.tolist(), seg.cell.tolist(), strict=True
    ):
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


def _thread_count(n_chunks: int) -> int:
    """Threads for the chunk loops: the CPUs this process may use, at most one per chunk."""
    return max(1, min(n_chunks, len(os.sched_getaffinity(0)), _MAX_THREADS))


def _over_chunks(chunks: list[_Chunk], work: Callable[[Sequence[_Chunk]], object]) -> list:
    """`work` on the chunks dealt round-robin to one share per thread; the shares' results.

    The chunk loops are NumPy vector operations that release the GIL, so threads use
    every core (the fit's dominant cost on multi-million-point problems).
    """
    n = _thread_count(len(chunks))
    shares = [chunks[k::n] for k in range(n)]
    if n == 1:
        return [work(shares[0])]
    with ThreadPoolExecutor(n) as pool:
        return list(pool.map(work, shares))


def ray_terms(
    xp: ModuleType, comps: Any, rc: Any, tc: Any, screen: Any, jacobian: bool
) -> tuple[Any, ...]:
    """Residuals (Q-S) mm (2,n) and ok mask of pixels of one pose with spline components
    comps (C,n) [+ G = dQ/dcomponents (2,C,n), J = dQ/dpose (2,6,n)]; arrays of module xp."""
    c = len(comps)
    if jacobian:
        r, jr = expmap_jacobian_rows(comps[0], comps[1], xp=xp)
    else:
        r = expmap_rows(comps[0], comps[1], xp=xp)
    r_s = rc @ r
    o_s = rc[:, :2] @ comps[2:4] + tc[:, None] if c == 4 else xp.broadcast_to(tc[:, None], r.shape)
    ok = r_s[2] * o_s[2] < 0  # the ray moves towards the plane
    rz = xp.where(ok, r_s[2], 1.0)
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
    g^T W g and xg (7C,n), [a, q]: (g^T W jp)[a, q], q = 6: (g^T W e)[a]."""
    iu, ju = tri
    c, n = g.shape[1:]
    gw = g * ws[:, None, :]
    hp = gw[0, iu] * g[0, ju] + gw[1, iu] * g[1, ju]
    xg = xp.empty((c, 7, n))
    xg[:, _JP_DENSE] = gw[0, :, None] * jp[0, _JP_DENSE] + gw[1, :, None] * jp[1, _JP_DENSE]
    xg[:, 3], xg[:, 4] = gw[0], gw[1]  # jp[:, 3] = (1, 0), jp[:, 4] = (0, 1)
    xg[:, 6] = gw[0] * e[0] + gw[1] * e[1]
    return hp, xg.reshape(7 * c, n)


class _Problem:
    """Fixed per-fit geometry: pixels sorted by (pose, cell), local cell coordinates, blocks.

    Per-pixel arrays are feature-major ((k, N), rows contiguous) so every step is a
    plain vector operation. Inside a cell the 16 basis weights are K m(s, t) with m the
    16 monomials t^l s^k (`monomial_basis`), so sum_p (w w^T) h_p = K [sum_p m m^T h_p] K^T
    needs only the 49 moments sum_p t^L s^M h_p (L, M <= 6) per cell: one small matrix
    product per (pose, cell) group.
    """

    def __init__(self, grid: SplineGrid, n_comp: int, obs: list[PoseObs]) -> None:
        self.grid, self.c = grid, n_comp
        self.n_spline = grid.size * n_comp
        self.n_pose = len(obs)
        self.n = self.n_spline + 6 * self.n_pose
        self.n_cells = grid.cells[0] * grid.cells[1]
        pix = np.concatenate([o.pixels for o in obs])
        pose_of = np.concatenate([np.full(len(o.pixels), j) for j, o in enumerate(obs)])
        cell, s, t = grid.local(pix[:, 0], pix[:, 1])
        order = np.argsort(radix_keys(pose_of * self.n_cells + cell), kind="stable")
        self.inverse = np.empty_like(order)
        self.inverse[order] = np.arange(len(order))
        self.s, self.t = s[order], t[order]
        self.screen = np.ascontiguousarray(np.concatenate([o.screen_mm for o in obs])[order].T)
        self.sigma = np.ascontiguousarray(np.concatenate([o.sigma_mm for o in obs])[order].T)
        self.inv_sigma = 1.0 / self.sigma
        self.counts = np.array([len(o.pixels) for o in obs])
        self.segments = _segments(pose_of[order], cell[order])
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
        return np.split(values.T[self.inverse], np.cumsum(self.counts)[:-1])

    def _chunk(
        self, st: LMState, poly: np.ndarray, ch: _Chunk, jacobian: bool
    ) -> tuple[np.ndarray, ...]:
        """Residuals (Q-S) mm (2,n) and ok mask of a block [+ monomials, G (2,C,n), J (2,6,n)]."""
        m16 = monomials(self.s[ch.a : ch.b], self.t[ch.a : ch.b], 3)
        comps = np.empty((self.c, ch.b - ch.a))
        for a, b, cell in ch.groups:
            np.matmul(poly[cell], m16[:, a:b], out=comps[:, a:b])
        screen = self.screen[:, ch.a : ch.b]
        out = ray_terms(np, comps, st.rc[ch.pose], st.tc[ch.pose], screen, jacobian)
        if not jacobian:
            return out
        res, ok, g, jp = out
        return res, ok, m16, g, jp

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
        self, st: LMState, poly: np.ndarray, wt: np.ndarray, share: Sequence[_Chunk], spline: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Normal-equation sums of a share of chunks: per-cell moments, spline-pose cross
        moments, and the per-pose blocks (see `normal_equations`)."""
        c, nc, npo = self.c, self.n_cells, self.n_pose
        mom = np.zeros((nc, 49, len(self.tri[0])))  # sum m49 * (g^T W g)[upper triangle]
        cross = np.zeros((npo, nc, 16, 7 * c))  # sum m16 * xg (see `spline_terms`)
        hpp, gpp = np.zeros((npo, 6, 6)), np.zeros((npo, 6))
        for ch in share:
            e, _, m16, g, jp = self._chunk(st, poly, ch, jacobian=True)
            ws = wt[ch.a : ch.b] * self.inv_sigma[:, ch.a : ch.b] ** 2  # (2,n)
            hpp_c, gpp_c = pose_terms(np, e, jp, ws)
            hpp[ch.pose] += hpp_c
            gpp[ch.pose] += gpp_c
            if not spline:
                continue
            hp, xg = spline_terms(np, e, g, jp, ws, self.tri)
            m49 = monomials(self.s[ch.a : ch.b], self.t[ch.a : ch.b], 6)
            for a, b, cell in ch.groups:  # np.dot, not @: it releases the GIL for threads
                mom[cell] += np.dot(m49[:, a:b], hp[:, a:b].T)
                cross[ch.pose, cell] += np.dot(m16[:, a:b], xg[:, a:b].T)
        return mom, cross, hpp, gpp

    def normal_equations(
        self, st: LMState, wt: np.ndarray, spline: bool = True
    ) -> tuple[np.ndarray, np.ndarray]:
        """J^T W J and J^T W e from per-cell monomial moments (spline) and per-pose sums."""
        poly = self.polynomials(st.coeffs)
        parts = _over_chunks(
            self.chunks, lambda share: self._moments(st, poly, wt, share, spline)
        )
        mom, cross, hpp, gpp = (sum(p[k] for p in parts) for k in range(4))
        return self.assemble(hpp, gpp, (mom, cross) if spline else None)

    def assemble(
        self, hpp: np.ndarray, gpp: np.ndarray, moments: tuple[np.ndarray, np.ndarray] | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """J^T W J and J^T W e from the per-pose sums and, unless the spline is fixed (None),
        the per-cell moments (nc,49,nt) and per-(pose, cell) cross moments (npo,nc,16,7C)."""
        c, ns, nc, npo = self.c, self.n_spline, self.n_cells, self.n_pose
        iu, ju = self.tri
        h, grad = np.zeros((self.n, self.n)), np.zeros(self.n)
        for j in range(npo):
            sl = slice(ns + 6 * j, ns + 6 * j + 6)
            h[sl, sl], grad[sl] = hpp[j], gpp[j]
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
        hsp = np.zeros((ns, 6 * npo))
        for j in range(npo):
            blk_j = xk[j].reshape(nc, 16, c, 7)[..., :6].reshape(nc, 16 * c, 6)
            np.add.at(hsp, (cols[:, :, None], 6 * j + np.arange(6)), blk_j)
        h[:ns, ns:] = hsp
        h[ns:, :ns] = hsp.T
        np.add.at(grad, cols, xk.sum(axis=0).reshape(nc, 16, c, 7)[..., 6].reshape(nc, 16 * c))
        return h, grad


def _robust(s: np.ndarray, k: float, cut: float) -> tuple[np.ndarray, np.ndarray]:
    """Truncated-Huber cost per residual norm s and its IRLS weight."""
    hub = np.where(s <= k, s * s, 2 * k * s - k * k)
    cost = np.minimum(hub, 2 * k * cut - k * k)
    wt = np.where(s <= k, 1.0, k / np.maximum(s, 1e-300)) * (s <= cut)
    return cost, wt


def gauge_constraints(grid: SplineGrid, n_comp: int, n_total: int) -> np.ndarray:
    """Rows of the linear gauge constraints (see module docstring) on the parameter vector."""
    w_img, h_img = grid.image_size
    cu, cv = (w_img - 1) / 2, (h_img - 1) / 2
    idx, w, wdu, wdv = grid.basis(np.array([cu]), np.array([cv]), derivatives=True)
    idx, w, wdu, wdv = idx[0], w[0], wdu[0], wdv[0]
    rows = []

    def row(comp_weights: list[tuple[int, np.ndarray]]) -> np.ndarray:
        r = np.zeros(n_total)
        for comp, weights in comp_weights:
            r[idx * n_comp + comp] += weights
        return r

    rows += [row([(0, w)]), row([(1, w)]), row([(1, wdu)])]
    if n_comp == 4:
        rows += [row([(2, w)]), row([(3, w)]), row([(2, wdu), (3, wdv)])]
    return np.array(rows)


def _apply_pose_step(st: LMState, dp: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Poses after the left-multiplied update exp(omega), + dt."""
    rcs, tcs = [], []
    for j, (rc, tc) in enumerate(zip(st.rc, st.tc, strict=True)):
        om, dt = dp[6 * j : 6 * j + 3], dp[6 * j + 3 : 6 * j + 6]
        rot = Rotation.from_rotvec(om).as_matrix()
        rcs.append(rot @ rc)
        tcs.append(rot @ tc + dt)
    return rcs, tcs


@dataclass
class _Loop:
    """LM state carried across iterations and phases."""

    state: LMState
    z: np.ndarray  # free directions (gauge null space or poses only)
    prior_base: np.ndarray
    mu: float = 1e-3
    it: int = 0
    history: list[float] = field(default_factory=list)
    converged: bool = False
    cut: float = np.inf
    lam_prior: float = 0.0
    res: np.ndarray | None = None  # residuals (2,N) and ok mask of `state`
    ok: np.ndarray | None = None
    hr: np.ndarray | None = None  # reduced normal matrix (with prior) of the last iteration


def _make_problem(
    grid: SplineGrid, n_comp: int, obs: list[PoseObs], xp: str
) -> _Problem | DeviceProblem:
    """The fit's per-pixel problem: threaded NumPy ("numpy") or `DeviceProblem` on the array
    module named by xp ("cupy"; `array_module` says clearly when it is missing)."""
    prob = _Problem(grid, n_comp, obs)
    if xp == "numpy":
        return prob
    from calibration.fit.sgcc_device import DeviceProblem  # it imports this module

    return DeviceProblem(prob, array_module(xp))


def _subset(obs: list[PoseObs], target: int) -> list[PoseObs] | None:
    """Every k-th point of each pose (about `target` in all), or None when not worth it."""
    k = sum(len(o.pixels) for o in obs) // max(target, 1)
    if k < 4:
        return None
    return [PoseObs(o.pixels[::k], o.screen_mm[::k], o.sigma_mm[::k]) for o in obs]


def _sigma_norm(prob: _Problem | DeviceProblem, res: np.ndarray) -> np.ndarray:
    """Residual norms in sigmas (Mahalanobis with diagonal screen sigmas)."""
    r0, r1 = res[0] * prob.inv_sigma[0], res[1] * prob.inv_sigma[1]
    return np.sqrt(r0 * r0 + r1 * r1)


def _cost(
    prob: _Problem | DeviceProblem,
    res: np.ndarray,
    ok: np.ndarray,
    x: np.ndarray,
    lp: _Loop,
    k: float,
) -> float:
    """Robust data cost (rays missing the plane pay the cap) plus the smoothness prior."""
    cost, _ = _robust(_sigma_norm(prob, res), k, lp.cut)
    cost = np.where(ok, cost, 2 * k * lp.cut)
    return float(cost.sum() + lp.lam_prior * x @ lp.prior_base @ x)


def _damped_factors(hs: np.ndarray, mu: float) -> Iterator[tuple[float, tuple]]:
    """(mu, Cholesky factor of hs + mu I) to try in turn: first the undamped Gauss-Newton
    system once damping has fallen below `_GAUSS_NEWTON_BELOW` (the quadratic model has
    proven good: weak modes then converge in one step instead of one decade of mu per
    iteration), then damping growing tenfold. Non-positive-definite systems are skipped."""
    mus = [0.0] if mu <= _GAUSS_NEWTON_BELOW else []
    mus += [mu * 10.0**k for k in range(_DAMPING_TRIES)]
    for m in mus:
        try:
            yield m, cho_factor(hs + m * np.eye(len(hs)))
        except np.linalg.LinAlgError:
            continue


def _iterate(
    prob: _Problem | DeviceProblem,
    lp: _Loop,
    options: LMOptions,
    last_it: int,
    progress: Callable[[int, int, str], None] | None,
    cancelled: Callable[[], bool] | None,
) -> None:
    """LM iterations on `prob` until converged or iteration `last_it`; updates `lp` in place."""
    ns = prob.n_spline
    res, ok = prob.residuals(lp.state)
    lp.converged = False
    first = True
    while lp.it < last_it:
        lp.it += 1
        if cancelled is not None and cancelled():
            from calibration.worker.executor import JobCancelled  # the worker's own signal

            raise JobCancelled("sgcc: calibration cancelled")
        st = lp.state
        s = _sigma_norm(prob, res)
        med = float(np.median(s[ok])) if ok.any() else 1.0
        lp.cut = max(options.cut_sigmas, 4.0 * 1.4826 * med)
        _, wt = _robust(s, options.huber_k, lp.cut)
        h, grad = prob.normal_equations(st, wt * ok, spline=not options.fix_spline)
        if first:
            diag_mean = float(np.mean(np.diag(h)[:ns])) if ns else 0.0
            lp.lam_prior = 0.0 if options.fix_spline else options.smooth * max(diag_mean, 1e-12)
            first = False
        x = st.coeffs.ravel()
        h[:ns, :ns] += lp.lam_prior * lp.prior_base
        grad[:ns] += lp.lam_prior * lp.prior_base @ x
        hr = lp.hr = lp.z.T @ h @ lp.z
        gr = lp.z.T @ grad
        cost0 = _cost(prob, res, ok, x, lp, options.huber_k)
        # The covariance is inflated by chi^2/dof when the model misfits; so is the tolerance.
        chi2_scale = max(1.0, cost0 / max(2 * int(ok.sum()) - len(hr), 1))
        accepted = False
        cost1 = cost0
        jac_scale = 1.0 / np.sqrt(np.maximum(np.diag(hr), 1e-300))
        hs = hr * jac_scale[:, None] * jac_scale[None, :]
        gs = gr * jac_scale
        near_optimum = False
        for mu, factor in _damped_factors(hs, lp.mu):
            ds = cho_solve(factor, -gs)
            if mu == 0.0:  # -g^T dx: the chi^2 drop a full Gauss-Newton step predicts
                near_optimum = float(-gs @ ds) <= options.chi2_tol * chi2_scale
            step = lp.z @ (jac_scale * ds)
            rcs, tcs = _apply_pose_step(st, step[ns:])
            cand = LMState(st.coeffs + step[:ns].reshape(st.coeffs.shape), rcs, tcs)
            res1, ok1 = prob.residuals(cand)
            cost1 = _cost(prob, res1, ok1, cand.coeffs.ravel(), lp, options.huber_k)
            if cost1 <= cost0:
                lp.state, res, ok = cand, res1, ok1
                lp.mu = max((mu or lp.mu) / 10, 1e-15)
                accepted = True
                break
        else:
            lp.mu *= 10.0**_DAMPING_TRIES
        lp.history.append(cost1 if accepted else cost0)
        if progress is not None:
            msg = f"LM iteration {lp.it}, cost {lp.history[-1]:.6g}"
            progress(lp.it, options.max_iterations, msg)
        small = (cost0 - cost1) <= options.rel_tol * max(cost0, 1e-300)
        if not accepted or small or near_optimum:
            lp.converged = True
            break
    lp.res, lp.ok = res, ok


def run_lm(
    grid: SplineGrid,
    n_comp: int,
    obs: list[PoseObs],
    init: LMState,
    options: LMOptions,
    *,
    progress: Callable[[int, int, str], None] | None = None,
    cancelled: Callable[[], bool] | None = None,
) -> LMResult:
    """Minimize the robust, uncertainty-weighted screen-plane residual; state and covariance.

    Large problems first converge on an even subset of about `options.subset_pixels`
    points (cheap iterations, at most half of `max_iterations`); the final iterations,
    the outlier decisions and the covariance use every point. At convergence the
    covariance reuses the last iteration's normal equations: exact when its step was
    rejected, else evaluated one Gauss-Newton step (chi^2 change <= chi2_tol, well inside
    the uncertainty) before the final state.
    BLAS runs single-threaded here: the dense solves are small and threads only contend.
    """
    with single_thread_blas():
        return _run(grid, n_comp, obs, init, options, progress, cancelled)


def _run(
    grid: SplineGrid,
    n_comp: int,
    obs: list[PoseObs],
    init: LMState,
    options: LMOptions,
    progress: Callable[[int, int, str], None] | None,
    cancelled: Callable[[], bool] | None,
) -> LMResult:
    """Body of `run_lm`."""
    ns = grid.size * n_comp
    n = ns + 6 * len(obs)
    if options.fix_spline:
        z = np.zeros((n, 6 * len(obs)))
        z[ns:, :] = np.eye(6 * len(obs))
    else:
        z = null_space(gauge_constraints(grid, n_comp, n))
    dmat = second_differences(grid)
    lp = _Loop(
        LMState(init.coeffs.copy(), [r.copy() for r in init.rc], [t.copy() for t in init.tc]),
        z,
        np.kron(dmat.T @ dmat, np.eye(n_comp)),
    )
    sub = _subset(obs, options.subset_pixels)
    if sub is not None:
        _iterate(_make_problem(grid, n_comp, sub, options.xp), lp, options,
                 options.max_iterations // 2, progress, cancelled)
    prob = _make_problem(grid, n_comp, obs, options.xp)
    _iterate(prob, lp, options, options.max_iterations, progress, cancelled)
    st, res, ok = lp.state, lp.res, lp.ok
    s = _sigma_norm(prob, res)
    cost_terms, wt = _robust(s, options.huber_k, lp.cut)
    wt = wt * ok
    hr = lp.hr
    if not lp.converged or hr is None:  # the last normal equations are not at `st`
        h, _ = prob.normal_equations(st, wt, spline=not options.fix_spline)
        h[:ns, :ns] += lp.lam_prior * lp.prior_base
        hr = z.T @ h @ z
    dscale = 1.0 / np.sqrt(np.maximum(np.diag(hr), 1e-300))
    min_eig = float(np.linalg.eigvalsh(hr * dscale[:, None] * dscale[None, :])[0])
    inl = wt > 0
    dof = max(2 * int(inl.sum()) - hr.shape[0], 1)
    chi2_dof = float(np.sum(s[inl] ** 2) / dof)
    cov = z @ np.linalg.inv(hr) @ z.T * max(1.0, chi2_dof)
    return LMResult(
        state=st,
        iterations=lp.it,
        converged=lp.converged,
        cost=float(cost_terms[ok].sum()),
        covariance=cov,
        min_eig=min_eig,
        residuals=prob.unsort(res),
        inliers=prob.unsort(inl),
        chi2_dof=chi2_dof,
        history=lp.history,
    )
