"""Levenberg–Marquardt for sGCC ray-field splines and screen poses (docs/physics.md section 6).

Residual of pixel p in pose j: the model ray, moved into the screen frame
(o_s = Rc o + tc, r_s = Rc r with Rc = R_j^T, tc = -R_j^T t_j), meets the plane z = 0 at
Q; e = (Q - S_p) / sigma_p (screen mm over screen mm: a Mahalanobis distance).
Normal equations: every residual touches the 16 control points of its cell and its pose's
6 parameters, so they are accumulated per (pose, cell) group from monomial moments with
small matrix products (see `Problem`; no loop over pixels). Large fits converge on an
even subset first (`run_lm`). Robustness: Huber weights (k = 3) with a hard cut at
`cut` sigmas (redescending; pixels beyond it are treated as outliers).

Gauge (explicit, linear constraints kept exact by stepping in their null space):
- per pixel: r is unit by construction (exp-map coordinates), o_z = 0;
- rotation of the camera frame: a(c) = b(c) = 0 and db/du(c) = 0 at the sensor center c
  (the center ray is +z and its u-derivative lies in the x-z plane);
- translation (non-central only): ox(c) = oy(c) = 0 and dox/du(c) + doy/dv(c) = 0.
A weak second-difference prior (relative weight `smooth`) defines control points without
data; where data exist it is negligible, where they do not its large covariance shows it.
`LMOptions.xp = "cupy"` moves the per-pixel work to a GPU (`calibration/fit/sgcc/device.py`).
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg import cho_factor, cho_solve, lapack
from scipy.spatial.transform import Rotation

from calibration.decode.arrays import array_module
from calibration.fit.observations import PoseObs
from calibration.fit.sgcc.gauge import GaugeBasis
from calibration.fit.sgcc.problem import Problem
from calibration.fit.sgcc.robust import block_weights, outlier_cut, robust_terms, sigma_norm
from calibration.fit.sgcc.state import LMOptions, LMResult, LMState
from calibration.metrology.screen_trace import N_SCREEN
from calibration.models.blas_threads import single_thread_blas
from calibration.models.bspline import (
    SplineGrid,
    second_differences,
)
from calibration.shared.progress import CancelCheck, Cancelled, ProgressFn

if TYPE_CHECKING:
    from calibration.fit.sgcc.device import DeviceProblem


_DAMPING_TRIES = 12  # LM damping increases per iteration before giving up
_GAUSS_NEWTON_BELOW = 1e-6  # Jacobi-scaled damping under which the undamped step goes first
_CHORD_MODEL_TOL = 0.1  # relative misfit of the predicted chi^2 drop that still allows chords


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
    z: GaugeBasis  # free directions (gauge null space or poses only)
    prior_base: np.ndarray
    mu: float = _GAUSS_NEWTON_BELOW  # first try the undamped step (a good OpenCV start)
    it: int = 0
    history: list[float] = field(default_factory=list)
    converged: bool = False
    cut: float = np.inf
    lam_prior: float = 0.0
    prior_mean: np.ndarray | float = 0.0  # centre of the prior (LMOptions.prior_mean)
    res: np.ndarray | None = None  # residuals (2,N), ok mask and norms (sigmas) of `state`
    ok: np.ndarray | None = None
    s: np.ndarray | None = None
    hr: np.ndarray | None = None  # reduced normal matrix (with prior) of the last iteration


def _on_device(prob: Problem, xp: str) -> Problem | DeviceProblem:
    """The fit's per-pixel problem: threaded NumPy ("numpy") or `DeviceProblem` on the array
    module named by xp ("cupy"; `array_module` says clearly when it is missing)."""
    if xp == "numpy":
        return prob
    from calibration.fit.sgcc.device import DeviceProblem  # it imports this module

    return DeviceProblem(prob, array_module(xp))


def _subset(obs: list[PoseObs], target: int) -> list[PoseObs] | None:
    """Every k-th point of each pose (about `target` in all), or None when not worth it."""
    k = sum(len(o.pixels) for o in obs) // max(target, 1)
    if k < 4:
        return None
    return [PoseObs(o.pixels[::k], o.screen_mm[::k], o.sigma_mm[::k]) for o in obs]


def _spd_inverse(a: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive-definite matrix from its Cholesky factor (half the
    work of a general inverse); a general inverse where the factorization fails."""
    c, info = lapack.dpotrf(a, lower=True)
    if info == 0:
        inv, info = lapack.dpotri(c, lower=True)
        if info == 0:
            return np.tril(inv) + np.tril(inv, -1).T
    return np.linalg.inv(a)


def _prior_cost(x: np.ndarray, lp: _Loop) -> float:
    """The smoothness prior's cost at coefficients x."""
    dx = x - lp.prior_mean
    return float(lp.lam_prior * dx @ lp.prior_base @ dx)


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
    prob: Problem | DeviceProblem,
    lp: _Loop,
    options: LMOptions,
    last_it: int,
    progress: ProgressFn | None,
    cancelled: CancelCheck | None,
) -> None:
    """LM iterations on `prob` until converged or iteration `last_it`; updates `lp` in place.

    After an accepted undamped (Gauss-Newton) step the next iteration is a chord step: the
    gradient alone at the new state (computed in the same pass as the candidate's residuals,
    `residuals_and_normal_equations`; anew if the outlier cut moved), solved with the
    previous factorization. Near the optimum the normal matrix hardly changes over a step, so
    the chord step's decrement certifies convergence without a second full pass; a rejected
    chord step falls back to a full iteration. The first iteration's normal equations come
    with the first residuals.
    """
    ns = prob.n_spline
    spline = not options.fix_spline
    # Residuals and normal equations in one pass, weighted with the cut the fit has (its
    # default at the start); computed anew below if the cut moves.
    cut = lp.cut if np.isfinite(lp.cut) else options.cut_sigmas
    res, ok, h, grad = prob.residuals_and_normal_equations(
        lp.state, block_weights(options.huber_k, cut), spline, hessian=True)
    # (cut, J^T W J or None (gradient only), J^T W e) at the current state, from its pass
    pre: tuple[float, np.ndarray | None, np.ndarray] | None = (cut, h, grad)
    s = None
    lp.converged = False
    first = True
    chord: tuple[tuple, np.ndarray] | None = None  # (factor, Jacobi scale) for a chord step
    while lp.it < last_it:
        lp.it += 1
        if cancelled is not None and cancelled():
            raise Cancelled("sgcc: calibration cancelled")
        st = lp.state
        s = sigma_norm(prob, res) if s is None else s  # kept from the accepted candidate
        lp.cut = outlier_cut(s, ok, options.cut_sigmas)
        data0, wt, _ = robust_terms(s, ok, options.huber_k, lp.cut)
        if pre is not None and pre[0] == lp.cut and (pre[1] is not None or chord is not None):
            h, grad = pre[1], pre[2]  # computed with the residuals of this state
        else:
            h, grad = prob.normal_equations(st, wt, spline=spline, hessian=chord is None)
        pre = None
        if first:
            diag_mean = float(np.mean(np.diag(h)[:ns])) if ns else 0.0
            lp.lam_prior = 0.0 if options.fix_spline else options.smooth * max(diag_mean, 1e-12)
            first = False
        x = st.coeffs.ravel()
        grad[:ns] += lp.lam_prior * lp.prior_base @ (x - lp.prior_mean)
        gr = lp.z.reduce_vector(grad)
        if chord is None:
            h[:ns, :ns] += lp.lam_prior * lp.prior_base
            hr = lp.hr = lp.z.reduce(h)
            jac_scale = 1.0 / np.sqrt(np.maximum(np.diag(hr), 1e-300))
            hs = hr * jac_scale[:, None] * jac_scale[None, :]
            tries = _damped_factors(hs, lp.mu)
        else:
            tries, jac_scale = iter([(0.0, chord[0])]), chord[1]
        cost0 = data0 + _prior_cost(x, lp)
        # The covariance is inflated by chi^2/dof when the model misfits; so is the tolerance.
        chi2_scale = max(1.0, cost0 / max(2 * int(ok.sum()) - len(lp.hr), 1))
        accepted, was_chord, chord = False, chord is not None, None
        cost1 = cost0
        gs = gr * jac_scale
        near_optimum, predicted = False, 0.0
        for mu, factor in tries:
            ds = cho_solve(factor, -gs)
            if mu == 0.0:  # -g^T dx: the chi^2 drop a full Gauss-Newton step predicts
                predicted = float(-gs @ ds)
                near_optimum = predicted <= options.chi2_tol * chi2_scale
            step = lp.z.expand(jac_scale * ds)
            rcs, tcs = _apply_pose_step(st, step[ns:])
            scr = None if st.screen is None else st.screen + step[ns + 6 * len(rcs):]
            cand = LMState(st.coeffs + step[:ns].reshape(st.coeffs.shape), rcs, tcs, scr)
            grad1 = None
            if mu == 0.0 and not was_chord:  # a chord step may follow: its gradient now
                res1, ok1, _, grad1 = prob.residuals_and_normal_equations(
                    cand, block_weights(options.huber_k, lp.cut), spline)
            else:
                res1, ok1 = prob.residuals(cand)
            s1 = sigma_norm(prob, res1)
            cost1 = robust_terms(s1, ok1, options.huber_k, lp.cut)[0]
            cost1 += _prior_cost(cand.coeffs.ravel(), lp)
            if cost1 <= cost0:
                lp.state, res, ok, s = cand, res1, ok1, s1
                accepted = True
                if not was_chord:
                    lp.mu = max((mu or lp.mu) / 10, 1e-15)
                    # chord next only where the quadratic model held over this step
                    good = abs(cost0 - cost1 - predicted) <= _CHORD_MODEL_TOL * predicted
                    chord = (factor, jac_scale) if mu == 0.0 and good else None
                    pre = None if chord is None or grad1 is None else (lp.cut, None, grad1)
                break
        else:
            if not was_chord:
                lp.mu *= 10.0**_DAMPING_TRIES
        lp.history.append(cost1 if accepted else cost0)
        if progress is not None:
            msg = f"LM iteration {lp.it}, cost {lp.history[-1]:.6g}"
            progress(lp.it, options.max_iterations, msg)
        small = accepted and (cost0 - cost1) <= options.rel_tol * max(cost0, 1e-300)
        if (not accepted and not was_chord) or small or (near_optimum and accepted):
            lp.converged = True
            break
    lp.res, lp.ok, lp.s = res, ok, s


def run_lm(
    grid: SplineGrid,
    n_comp: int,
    obs: list[PoseObs],
    init: LMState,
    options: LMOptions,
    *,
    progress: ProgressFn | None = None,
    cancelled: CancelCheck | None = None,
    problem: Problem | Future[Problem] | None = None,
) -> LMResult:
    """Minimize the robust, uncertainty-weighted screen-plane residual; state and covariance.

    `problem`: the full data's `Problem` (grid, n_comp, obs, options.screen), or its future,
    where the caller built it already (e.g. while it computed the start); else built here.

    Large problems first converge on an even subset of about `options.subset_pixels`
    points (cheap iterations, at most half of `max_iterations`); the final iterations,
    the outlier decisions and the covariance use every point. At convergence the
    covariance reuses the last full normal equations: exact when their step was rejected,
    else evaluated a Gauss-Newton step (and a chord step, `_iterate`) before the final
    state; for large problems that is the subset's optimum, a few sigma per coefficient
    away (standard deviations within ~0.2 %, docs/generic.md).
    BLAS runs single-threaded here: the dense solves are small and threads only contend.
    """
    with single_thread_blas():
        return _run(grid, n_comp, obs, init, options, progress, cancelled, problem)


def _run(
    grid: SplineGrid,
    n_comp: int,
    obs: list[PoseObs],
    init: LMState,
    options: LMOptions,
    progress: ProgressFn | None,
    cancelled: CancelCheck | None,
    problem: Problem | Future[Problem] | None,
) -> LMResult:
    """Body of `run_lm`."""
    ns = grid.size * n_comp
    screen = None  # fitted screen parameters after the poses (options.screen)
    if options.screen is not None:
        screen = np.zeros(N_SCREEN) if init.screen is None else init.screen.astype(float)
    n = ns + 6 * len(obs) + (0 if screen is None else N_SCREEN)
    if options.fix_spline:  # poses only: the spline and the screen stay fixed
        z = GaugeBasis.selection(n, np.arange(ns, ns + 6 * len(obs)))
    else:
        rows = gauge_constraints(grid, n_comp, n)
        if screen is not None and options.hold_glass:  # a gauge freedom (screen_terms.py)
            rows = np.vstack([rows, np.eye(n)[-1]])
        z = GaugeBasis.null_space_of(rows)
    dmat = second_differences(grid)
    lp = _Loop(
        LMState(init.coeffs.copy(), [r.copy() for r in init.rc], [t.copy() for t in init.tc],
                screen),
        z,
        np.kron(dmat.T @ dmat, np.eye(n_comp)) if options.prior_base is None
        else np.asarray(options.prior_base, dtype=np.float64),
    )
    if options.prior_mean is not None:
        lp.prior_mean = np.asarray(options.prior_mean, dtype=np.float64).ravel()
    sub = _subset(obs, options.subset_pixels)
    with ThreadPoolExecutor(1) as pool:
        if problem is None:  # sorted while the subset iterates (one core each)
            problem = Problem(grid, n_comp, obs, options.screen) if sub is None else pool.submit(
                Problem, grid, n_comp, obs, options.screen)
        if sub is not None:
            _iterate(_on_device(Problem(grid, n_comp, sub, options.screen), options.xp), lp,
                     options, options.max_iterations // 2, progress, cancelled)
        prob = _on_device(problem.result() if isinstance(problem, Future) else problem,
                          options.xp)
    _iterate(prob, lp, options, options.max_iterations, progress, cancelled)
    st, res, ok = lp.state, lp.res, lp.ok
    s = sigma_norm(prob, res) if lp.s is None else lp.s
    _, wt, cost = robust_terms(s, ok, options.huber_k, lp.cut)
    hr = lp.hr
    if not lp.converged or hr is None:  # the last normal equations are not at `st`
        h, _ = prob.normal_equations(st, wt, spline=not options.fix_spline)
        h[:ns, :ns] += lp.lam_prior * lp.prior_base
        hr = z.reduce(h)
    dscale = 1.0 / np.sqrt(np.maximum(np.diag(hr), 1e-300))
    min_eig = float(np.linalg.eigvalsh(hr * dscale[:, None] * dscale[None, :])[0])
    inl = wt > 0
    dof = max(2 * int(inl.sum()) - hr.shape[0], 1)
    chi2_dof = float(np.sum(s[inl] ** 2) / dof)
    cov = z.expand_matrix(_spd_inverse(hr)) * max(1.0, chi2_dof)
    return LMResult(
        state=st,
        iterations=lp.it,
        converged=lp.converged,
        cost=cost,
        covariance=cov,
        min_eig=min_eig,
        residuals=prob.unsort(res),
        inliers=prob.unsort(inl),
        chi2_dof=chi2_dof,
        history=lp.history,
        prior_weight=lp.lam_prior,
    )
