"""Levenberg–Marquardt for sGCC ray-field splines and screen poses (PHYSICS.md section 5).

Residual of pixel p in pose j: the model ray, moved into the screen frame
(o_s = Rc o + tc, r_s = Rc r with Rc = R_j^T, tc = -R_j^T t_j), meets the plane z = 0 at
Q; e = (Q - S_p) / sigma_p (screen mm over screen mm: a Mahalanobis distance).
Normal equations: every residual touches the 16 control points of its cell and its pose's
6 parameters, so they are accumulated per (pose, cell) group with one matrix product each
(no loop over pixels). Robustness: Huber weights (k = 3) with a hard cut at
`cut` sigmas (redescending; pixels beyond it are treated as outliers).

Gauge (explicit, linear constraints kept exact by stepping in their null space):
- per pixel: r is unit by construction (exp-map coordinates), o_z = 0;
- rotation of the camera frame: a(c) = b(c) = 0 and db/du(c) = 0 at the sensor center c
  (the center ray is +z and its u-derivative lies in the x-z plane);
- translation (non-central only): ox(c) = oy(c) = 0 and dox/du(c) + doy/dv(c) = 0.
A weak second-difference prior (relative weight `smooth`) defines control points without
data; where data exist it is negligible, where they do not its large covariance shows it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_factor, cho_solve, null_space
from scipy.spatial.transform import Rotation

from calibration.models.bspline import SplineGrid, second_differences
from calibration.models.sgcc import expmap_jacobian


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
    smooth: float = 1e-7
    rel_tol: float = 1e-10
    fix_spline: bool = False


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


class _Problem:
    """Fixed per-fit geometry: basis weights and (pose, cell) grouping of all residuals."""

    def __init__(self, grid: SplineGrid, n_comp: int, obs: list[PoseObs]) -> None:
        self.grid, self.c, self.obs = grid, n_comp, obs
        self.n_spline = grid.size * n_comp
        self.n_pose = len(obs)
        self.n = self.n_spline + 6 * self.n_pose
        pix = np.concatenate([o.pixels for o in obs])
        self.pose_of = np.concatenate([np.full(len(o.pixels), j) for j, o in enumerate(obs)])
        self.idx, self.w = grid.basis(pix[:, 0], pix[:, 1])
        key = self.pose_of * (grid.cells[0] * grid.cells[1]) + grid.cell_of(pix[:, 0], pix[:, 1])
        order = np.argsort(key, kind="stable")
        self.order = order
        k_sorted = key[order]
        starts = np.flatnonzero(np.r_[True, k_sorted[1:] != k_sorted[:-1]])
        self.bounds = np.r_[starts, len(order)]
        self.w_sorted = self.w[order]
        self.screen = np.concatenate([o.screen_mm for o in obs])
        self.sigma = np.concatenate([o.sigma_mm for o in obs])
        self.counts = np.array([len(o.pixels) for o in obs])
        ends = np.cumsum(self.counts)
        self.slices = [slice(int(e - n), int(e)) for e, n in zip(ends, self.counts, strict=True)]

    def evaluate(self, st: LMState, jacobian: bool) -> tuple[np.ndarray, ...]:
        """Residuals (Q-S) mm, ok mask [, G (N,2,C), pose Jacobian (N,2,6)]."""
        comps = np.einsum("nk,nkc->nc", self.w, st.coeffs[self.idx])
        r, jr = expmap_jacobian(comps[:, :2])
        o = np.zeros_like(r)
        if self.c == 4:
            o[:, :2] = comps[:, 2:4]
        o_s, r_s = np.empty_like(o), np.empty_like(r)
        for sl, rc_j, tc_j in zip(self.slices, st.rc, st.tc, strict=True):
            o_s[sl] = o[sl] @ rc_j.T + tc_j
            r_s[sl] = r[sl] @ rc_j.T
        ok = r_s[:, 2] * o_s[:, 2] < 0  # the ray moves towards the plane
        rz = np.where(ok, r_s[:, 2], 1.0)
        lam = -o_s[:, 2] / rz
        q = o_s[:, :2] + lam[:, None] * r_s[:, :2]
        res = np.where(ok[:, None], q - self.screen, 0.0)
        if not jacobian:
            return res, ok
        px, py = r_s[:, 0] / rz, r_s[:, 1] / rz  # dQ/d(o_s) = [[1, 0, -px], [0, 1, -py]]
        prc = np.empty((len(q), 2, 3))
        for sl, rc_j in zip(self.slices, st.rc, strict=True):
            prc[sl, 0] = rc_j[0] - px[sl, None] * rc_j[2]
            prc[sl, 1] = rc_j[1] - py[sl, None] * rc_j[2]
        g = np.empty((len(q), 2, self.c))
        g[:, :, :2] = lam[:, None, None] * (
            prc[:, :, 0, None] * jr[:, None, 0, :]
            + prc[:, :, 1, None] * jr[:, None, 1, :]
            + prc[:, :, 2, None] * jr[:, None, 2, :]
        )
        if self.c == 4:
            g[:, :, 2:] = prc[:, :, :2]
        qx, qy = q[:, 0], q[:, 1]
        jp = np.zeros((len(q), 2, 6))  # d/d(omega) = -dQ/d(o_s) [X]x, d/dt = dQ/d(o_s)
        jp[:, 0, 0], jp[:, 0, 1], jp[:, 0, 2] = -px * qy, px * qx, -qy
        jp[:, 1, 0], jp[:, 1, 1], jp[:, 1, 2] = -py * qy, py * qx, qx
        jp[:, 0, 3], jp[:, 1, 4] = 1.0, 1.0
        jp[:, 0, 5], jp[:, 1, 5] = -px, -py
        return res, ok, g, jp

    def normal_equations(
        self, g: np.ndarray, jp: np.ndarray, e: np.ndarray, wt: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """J^T W J and J^T W e, built per (pose, cell) group with batched products."""
        c, ns = self.c, self.n_spline
        h = np.zeros((self.n, self.n))
        grad = np.zeros(self.n)
        ws = wt[:, None] / self.sigma**2  # (N,2) per-row weights
        gw = g * ws[:, :, None]
        hp = np.einsum("nra,nrb->nab", gw, g).reshape(-1, c * c)[self.order]
        kp = np.einsum("nra,nrb->nab", gw, jp).reshape(-1, c * 6)[self.order]
        gp = np.einsum("nra,nr->na", gw, e)[self.order]
        pw = jp * ws[:, :, None]
        idx_sorted = self.idx[self.order]
        pose_sorted = self.pose_of[self.order]
        for j, sel in enumerate(self.slices):
            sl = slice(ns + 6 * j, ns + 6 * j + 6)
            h[sl, sl] += np.einsum("nra,nrb->ab", pw[sel], jp[sel])
            grad[sl] += np.einsum("nra,nr->a", pw[sel], e[sel])
        for a, b in zip(self.bounds[:-1], self.bounds[1:], strict=True):
            w = self.w_sorted[a:b]
            cols = (idx_sorted[a][:, None] * c + np.arange(c)).ravel()  # (16C,)
            blk = (w[:, :, None] * hp[a:b, None, :]).reshape(b - a, -1).T @ w  # (16*C*C, 16)
            blk = blk.reshape(16, c, c, 16).transpose(0, 1, 3, 2).reshape(16 * c, 16 * c)
            h[np.ix_(cols, cols)] += blk
            j = pose_sorted[a]
            sl = slice(ns + 6 * j, ns + 6 * j + 6)
            cross = (w.T @ kp[a:b]).reshape(16 * c, 6)
            h[cols, sl] += cross
            h[sl, cols] += cross.T
            grad[cols] += (w.T @ gp[a:b]).ravel()
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
    """Minimize the robust, uncertainty-weighted screen-plane residual; state and covariance."""
    prob = _Problem(grid, n_comp, obs)
    ns, n = prob.n_spline, prob.n
    if options.fix_spline:
        free = np.zeros((n, 6 * prob.n_pose))
        free[ns:, :] = np.eye(6 * prob.n_pose)
        z = free
    else:
        z = null_space(gauge_constraints(grid, n_comp, n))
    dmat = second_differences(grid)
    prior_base = np.kron(dmat.T @ dmat, np.eye(n_comp))
    st = LMState(init.coeffs.copy(), [r.copy() for r in init.rc], [t.copy() for t in init.tc])

    def sigma_norm(res: np.ndarray) -> np.ndarray:
        return np.hypot(res[:, 0] / prob.sigma[:, 0], res[:, 1] / prob.sigma[:, 1])

    def total(s: LMState, cut: float, lam_prior: float) -> float:
        res, ok = prob.evaluate(s, jacobian=False)
        cost, _ = _robust(sigma_norm(res), options.huber_k, cut)
        cost = np.where(ok, cost, 2 * options.huber_k * cut)
        x = s.coeffs.ravel()
        return float(cost.sum() + lam_prior * x @ prior_base @ x)

    mu = 1e-3
    history: list[float] = []
    converged = False
    it = 0
    lam_prior = 0.0
    cut = np.inf
    for it in range(1, options.max_iterations + 1):
        if cancelled is not None and cancelled():
            from calibration.worker.executor import JobCancelled  # the worker's own signal

            raise JobCancelled("sgcc: calibration cancelled")
        res, ok, g, jp = prob.evaluate(st, jacobian=True)
        s = sigma_norm(res)
        med = float(np.median(s[ok])) if ok.any() else 1.0
        cut = max(options.cut_sigmas, 4.0 * 1.4826 * med)
        _, wt = _robust(s, options.huber_k, cut)
        wt = wt * ok
        h, grad = prob.normal_equations(g, jp, res, wt)
        if it == 1:
            diag_mean = float(np.mean(np.diag(h)[:ns])) if ns else 0.0
            lam_prior = 0.0 if options.fix_spline else options.smooth * max(diag_mean, 1e-12)
        x = st.coeffs.ravel()
        h[:ns, :ns] += lam_prior * prior_base
        grad[:ns] += lam_prior * prior_base @ x
        hr = z.T @ h @ z
        gr = z.T @ grad
        cost0 = total(st, cut, lam_prior)
        accepted = False
        cost1 = cost0
        jac_scale = 1.0 / np.sqrt(np.maximum(np.diag(hr), 1e-300))
        hs = hr * jac_scale[:, None] * jac_scale[None, :]
        for _ in range(12):
            a = hs + mu * np.eye(len(hs))
            try:
                step = z @ (jac_scale * cho_solve(cho_factor(a), -gr * jac_scale))
            except np.linalg.LinAlgError:
                mu *= 10
                continue
            rcs, tcs = _apply_pose_step(st, step[ns:])
            cand = LMState(st.coeffs + step[:ns].reshape(st.coeffs.shape), rcs, tcs)
            cost1 = total(cand, cut, lam_prior)
            if cost1 <= cost0:
                st = cand
                mu = max(mu / 10, 1e-15)
                accepted = True
                break
            mu *= 10
        history.append(cost1 if accepted else cost0)
        if progress is not None:
            progress(it, options.max_iterations, f"LM iteration {it}, cost {history[-1]:.6g}")
        if not accepted or (cost0 - cost1) <= options.rel_tol * max(cost0, 1e-300):
            converged = True
            break
    res, ok, g, jp = prob.evaluate(st, jacobian=True)
    s = sigma_norm(res)
    cost_terms, wt = _robust(s, options.huber_k, cut)
    wt = wt * ok
    h, _ = prob.normal_equations(g, jp, res, wt)
    h[:ns, :ns] += lam_prior * prior_base
    hr = z.T @ h @ z
    dscale = 1.0 / np.sqrt(np.maximum(np.diag(hr), 1e-300))
    min_eig = float(np.linalg.eigvalsh(hr * dscale[:, None] * dscale[None, :])[0])
    inl = wt > 0
    dof = max(2 * int(inl.sum()) - hr.shape[0], 1)
    chi2_dof = float(np.sum(s[inl] ** 2) / dof)
    cov = z @ np.linalg.inv(hr) @ z.T * max(1.0, chi2_dof)
    splits = np.cumsum(prob.counts)[:-1]
    return LMResult(
        state=st,
        iterations=it,
        converged=converged,
        cost=float(cost_terms[ok].sum()),
        covariance=cov,
        min_eig=min_eig,
        residuals=np.split(res, splits),
        inliers=np.split(inl, splits),
        chi2_dof=chi2_dof,
        history=history,
    )
