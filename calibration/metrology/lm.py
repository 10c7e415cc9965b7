"""Weighted Levenberg-Marquardt of a parametric camera, its poses and the screen, on every pixel.

Residual of pixel p in pose j: where the model's ray for p reaches the panel
(calibration.metrology.screen), minus the decoded screen point, per axis, divided by
the decoded sigma (screen px): the maximum-likelihood fit for independent Gaussian
decoding noise (docs/physics.md section 6). Jacobians are analytic (directions.py,
screen.py); each residual touches the intrinsics, the screen parameters and its own
pose, so the normal equations are one small dense matrix, accumulated pose by pose with
BLAS. Pose update: R <- R exp([w]x), t <- t + dt. Covariance: the inverse normal matrix
scaled by the reduced chi-square.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from calibration.fit.correspondences import PointSet
from calibration.fit.result import PoseEstimate
from calibration.metrology.directions import directions
from calibration.metrology.screen import ScreenModel
from calibration.models.blas_threads import single_thread_blas
from calibration.models.parametric import PinholeFamily
from calibration.threads import map_in_threads

OUTLIER_SIGMAS = 5.0
MISFIT_RTOL = 1e-6  # `_levenberg_marquardt`: converged when a step removes less of the misfit
_CHUNK = 8192  # points per batch: the per-point temporaries stay in cache
_CHI_MEDIAN_2DOF = float(np.sqrt(2 * np.log(2)))  # median of |r| for a whitened 2D Gaussian


@dataclass
class DenseFit:
    """Result of `fit_dense`: estimates, 1-sigma and the fit's statistics."""

    model: PinholeFamily
    poses: list[PoseEstimate]
    screen: ScreenModel
    points: list[PointSet]  # the inliers used in the last round
    param_std: np.ndarray  # model parameters (0 where fixed)
    screen_std: np.ndarray  # screen parameters (empty for a flat screen)
    stats: dict[str, Any] = field(default_factory=dict)
    free: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # fitted params


def bmm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched small matrix product (N,i,j) @ (N,j,k) as j broadcast multiply-adds."""
    out = a[:, :, 0, None] * b[:, None, 0, :]
    for j in range(1, a.shape[2]):
        out += a[:, :, j, None] * b[:, None, j, :]
    return out


def rmul(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """(N,i,j) @ (j,k) for one shared matrix, as a single BLAS product."""
    return (a.reshape(-1, a.shape[2]) @ m).reshape(a.shape[0], a.shape[1], m.shape[1])


def cross_rows(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Each row of a (N,i,3) crossed with v (N,3): row . (v x w) = (row x v) . w."""
    ax, ay, az = a[:, :, 0], a[:, :, 1], a[:, :, 2]
    vx, vy, vz = v[:, None, 0], v[:, None, 1], v[:, None, 2]
    return np.stack([ay * vz - az * vy, az * vx - ax * vz, ax * vy - ay * vx], axis=2)


class _Problem:
    """Model + poses + screen over a fixed set of points; residuals and normal equations."""

    def __init__(self, model: PinholeFamily, poses: list[PoseEstimate], points: list[PointSet],
                 screen: ScreenModel, free: np.ndarray) -> None:
        self.model, self.screen, self.free = model, screen, np.flatnonzero(free)
        self.poses = [PoseEstimate(p.rotation.copy(), p.translation.copy()) for p in poses]
        self.set_points(points)

    def set_points(self, points: list[PointSet]) -> None:
        """Index every pose's pixels into one list of distinct pixels (directions once each)."""
        self.points = points
        allpix = np.concatenate([p.pixels for p in points])
        if np.all(allpix == np.round(allpix)) and allpix.min(initial=0) >= 0:
            key = allpix[:, 1].astype(np.int64) * (int(allpix[:, 0].max()) + 1) + allpix[:, 0]
            ukey, inverse = np.unique(key.astype(np.int64), return_inverse=True)
            first = np.zeros(ukey.size, dtype=np.int64)
            first[inverse] = np.arange(allpix.shape[0])
            self.pixels = allpix[first]
        else:
            self.pixels, inverse = allpix, np.arange(allpix.shape[0])
        splits = np.cumsum([len(p) for p in points])[:-1]
        self.index = np.split(inverse, splits)
        self.start: np.ndarray | None = None
        self._buffers: tuple | None = None  # `directions` outputs to fill again
        # per pose, the points whose residuals count: those finite at the first evaluation
        # on these points (a point the model cannot unproject there stays out, even if a
        # later start finds a root for it)
        self.support: list[np.ndarray] | None = None

    @property
    def sizes(self) -> tuple[int, int, int]:
        """(free intrinsics, screen parameters, total)."""
        ni, ns = self.free.size, self.screen.n_free
        return ni, ns, ni + ns + 6 * len(self.poses)

    def _pose_terms(self, j: int, sl: slice, dirs: np.ndarray, jdir: np.ndarray | None,
                    want_jac: bool):
        """Whitened residuals (2N,) of points `sl` of pose j and, if asked, their Jacobian
        blocks (2N, ni+ns+6)."""
        pts, pose = self.points[j], self.poses[j]
        rot, idx = pose.rotation, self.index[j][sl]
        pitch, sigma, screen_px = np.asarray(pts.pitch_mm), pts.sigma_px[sl], pts.screen_px[sl]
        d = dirs[idx] @ rot  # R^T d_c, row-wise
        o = np.broadcast_to(-(rot.T @ pose.translation), d.shape)
        q = d[:, :2] / d[:, 2:3]
        qpts, jac = self.screen.trace(o, q, want_jac)
        scale = 1.0 / (pitch[None, :] * sigma)  # (N, 2)
        res = (qpts / pitch[None, :] - screen_px) / sigma
        if not want_jac:
            return res.ravel(), None
        n = len(idx)
        dqdd = np.zeros((n, 2, 3))
        dqdd[:, 0, 0] = dqdd[:, 1, 1] = 1.0 / d[:, 2]
        dqdd[:, :, 2] = -q / d[:, 2:3]
        if self.screen.mode == "flat":  # dQ/dq = -o_z I
            jqd = -o[:, 2, None, None] * dqdd
        else:
            jqd = bmm(jac["q"], dqdd)  # d(panel point)/d(ray direction in the screen frame)
        ni, ns, _ = self.sizes
        blk = np.empty((n, 2, ni + ns + 6))
        if ni:
            assert jdir is not None
            jd = jdir[idx][:, :, self.free]
            rows = 2 if not np.any(jd[:, 2]) else 3  # pinhole directions have d_z = 1
            blk[:, :, :ni] = bmm(rmul(jqd, rot.T)[:, :, :rows], jd[:, :rows])
        if ns:
            blk[:, :, ni:ni + ns] = jac["s"]
        blk[:, :, ni + ns:ni + ns + 3] = cross_rows(jqd, d) + cross_rows(jac["o"], o)
        blk[:, :, ni + ns + 3:] = -rmul(jac["o"], rot.T)
        blk *= scale[:, :, None]
        return res.ravel(), blk.reshape(2 * n, -1)

    def evaluate(self, want_jac: bool):
        """Total cost, per-pose residuals, and (if asked) the normal matrix and gradient;
        chunks of points over threads, their sums added in one fixed order."""
        dirs, jdir, start = directions(self.model, self.pixels, self.start, want_jac,
                                       out=self._buffers)
        self.start = start
        if want_jac:  # the next evaluation fills the same arrays
            self._buffers = (dirs, jdir, start)
        ni, ns, ntot = self.sizes
        tasks = [(j, slice(a, a + _CHUNK)) for j in range(len(self.poses))
                 for a in range(0, len(self.index[j]), _CHUNK)]

        def terms(task: tuple[int, slice]) -> tuple[np.ndarray, float, Any, Any]:
            return self._chunk_terms(*task, dirs, jdir, want_jac)

        done = map_in_threads(terms, tasks)
        hmat, grad = np.zeros((ntot, ntot)), np.zeros(ntot)
        parts: list[list[np.ndarray]] = [[] for _ in self.poses]
        cost = 0.0
        for (j, _), (res, chunk_cost, h, g) in zip(tasks, done, strict=True):
            parts[j].append(res)
            cost += chunk_cost
            if h is not None:
                cols = np.r_[np.arange(ni + ns), ni + ns + 6 * j + np.arange(6)]
                hmat[np.ix_(cols, cols)] += h
                grad[cols] += g
        residuals = [np.concatenate(p) if p else np.zeros(0) for p in parts]
        if self.support is None:
            self.support = [np.isfinite(r[0::2]) & np.isfinite(r[1::2]) for r in residuals]
        return cost, residuals, hmat, grad

    def _chunk_terms(self, j: int, sl: slice, dirs: np.ndarray, jdir: np.ndarray | None,
                     want_jac: bool) -> tuple[np.ndarray, float, Any, Any]:
        """One chunk's residuals, cost and (if asked) normal-matrix and gradient terms. The
        cost is infinite where a point of the support has no residual (the parameters left
        the region where the model unprojects it: a step there is rejected, not rewarded by
        a smaller sum); points outside the support get NaN residuals."""
        res, blk = self._pose_terms(j, sl, dirs, jdir, want_jac)
        ok = np.isfinite(res)
        lost = False
        if self.support is not None:
            counted = np.repeat(self.support[j][sl], 2)
            lost = bool(np.any(counted & ~ok))
            res[~counted] = np.nan
            ok &= counted
        cost = np.inf if lost else float(res[ok] @ res[ok])
        if blk is None:
            return res, cost, None, None
        ok &= np.isfinite(blk.sum(axis=1))
        if not ok.all():
            blk[~ok] = 0.0
        return res, cost, blk.T @ blk, blk.T @ np.where(ok, res, 0.0)

    def params(self) -> tuple:
        """A snapshot of the state: model params, screen params, poses and the warm start of
        the model's iterative unprojection (`directions`)."""
        return (self.model.get_params().copy(), self.screen.params.copy(),
                [PoseEstimate(p.rotation.copy(), p.translation.copy()) for p in self.poses],
                None if self.start is None else self.start.copy())

    def restore(self, snap: tuple) -> None:
        """Go back to a snapshot, warm start included: an evaluation at rejected parameters
        leaves no trace (where a wide-angle model's unprojection has more than one root, a
        start left by such a trial could lead the next evaluation to another root, and the
        cost at the same parameters would depend on the trials made before)."""
        self.model.set_params(snap[0])
        self.screen.params = snap[1].copy()
        self.poses = [PoseEstimate(p.rotation.copy(), p.translation.copy()) for p in snap[2]]
        if snap[3] is None or self.start is None or self.start.shape != snap[3].shape:
            self.start = None if snap[3] is None else snap[3].copy()
        else:
            self.start[...] = snap[3]  # (in place: the array is one of the reused buffers)

    def step(self, delta: np.ndarray) -> None:
        """Apply a parameter update in the normal equations' layout."""
        ni, ns, _ = self.sizes
        v = self.model.get_params()
        v[self.free] += delta[:ni]
        self.model.set_params(v)
        if ns:
            self.screen.params = self.screen.params + delta[ni:ni + ns]
        for j, pose in enumerate(self.poses):
            dp = delta[ni + ns + 6 * j:ni + ns + 6 * j + 6]
            pose.rotation = pose.rotation @ cv2.Rodrigues(dp[:3].reshape(3, 1))[0]
            pose.translation = pose.translation + dp[3:]


def _levenberg_marquardt(prob: _Problem, max_iter: int, tol: float,
                         report: Callable[[str], None]) -> tuple[tuple, int, bool]:
    """Minimize the problem's cost in place; returns (last evaluation, iterations, converged).

    Stops when a step lowers (or would by the quadratic model lower) the cost, a sum of
    whitened squares, by less than `tol` times the residuals' robust variance scale (at
    least 1): it moves the parameters by << 1 of their reported sigma, which the reduced
    chi-square scales. Where the model cannot reach the noise floor, also when a step
    removes less than `MISFIT_RTOL` of the misfit left (the cost above the noise's
    expectation): such a model crawls along flat valleys for dozens of iterations that
    move its chi-square by < 0.1 % (measured on a 150-degree fisheye: 100 more iterations
    moved opencv5's ray error by 0.6 %; opencv-rational's stopping points along its valley
    had ray errors of 0.23-0.29 mrad at reduced chi-squares of 2.398-2.402, which the data
    cannot tell apart). A step's first trial is evaluated with the Jacobian (it is usually
    accepted); after a rejection, trials evaluate the cost only, and the Jacobian follows
    at the accepted point.
    """
    state = prob.evaluate(True)
    counted = sum(int(np.isfinite(r).sum()) for r in state[1])  # (fixed by the support)
    noise_tol = tol * max(1.0, robust_scale(state[1]) ** 2)
    lam, it = 1e-8, 0
    for it in range(1, max_iter + 1):
        cost, _, hmat, grad = state
        tol = max(noise_tol, MISFIT_RTOL * max(cost - counted, 0.0))  # the misfit left now
        diag = np.maximum(np.diag(hmat), 1e-300)
        snap = prob.params()
        with_jac = True
        while True:
            try:
                delta = np.linalg.solve(hmat + lam * np.diag(diag), -grad)
            except np.linalg.LinAlgError:
                delta = np.full_like(grad, np.nan)
            if np.all(np.isfinite(delta)):
                if -2 * grad @ delta - delta @ hmat @ delta < tol:
                    return state, it, True  # the next step would gain nothing measurable
                prob.step(delta)
                trial = prob.evaluate(with_jac)
                if not with_jac and np.isfinite(trial[0]) and trial[0] <= cost:
                    trial = prob.evaluate(True)
                if np.isfinite(trial[0]) and trial[0] <= cost:
                    break
                prob.restore(snap)
                with_jac = False
            lam *= 8.0
            if lam > 1e12:
                return state, it, True  # no descent direction left: at the minimum
        state = trial
        report(f"iteration {it}: cost {state[0]:.6f} (-{cost - state[0]:.3g}), lambda {lam:.2g}")
        lam = max(lam / 4.0, 1e-12)
        if cost - state[0] < tol:
            return state, it, True
    return state, it, False


def robust_scale(residuals: list[np.ndarray]) -> float:
    """The whitened residuals' scale from their median 2D norm (1 for pure noise): robust to
    the gross decoding outliers that a mean of squares would count."""
    norms = np.concatenate([np.hypot(r[0::2], r[1::2]) for r in residuals])
    if not np.isfinite(norms).any():
        return 1.0
    return float(np.nanmedian(norms)) / _CHI_MEDIAN_2DOF


def _outliers(residuals: list[np.ndarray]) -> list[np.ndarray]:
    """Keep-masks: whitened residual norm within max(5, sqrt(2 ln(100 N))) robust sigmas.

    The second bound is where N Gaussian inliers lose 0.01 points on average, so a fit
    on millions of points does not trim its own tails.
    """
    norms = [np.hypot(r[0::2], r[1::2]) for r in residuals]
    size = sum(nm.size for nm in norms)
    limit = max(OUTLIER_SIGMAS, float(np.sqrt(2 * np.log(100 * size)))) * max(
        1.0, robust_scale(residuals))
    return [np.isfinite(nm) & (nm <= limit) for nm in norms]


def fit_dense(model: PinholeFamily, poses: list[PoseEstimate], points: list[PointSet],
              screen: ScreenModel, free: np.ndarray, *, outlier_rounds: int = 2,
              max_iter: int = 50, tol: float = 1e-2, subset_points: int = 30000,
              progress: Callable[[str], None] | None = None) -> DenseFit:
    """Refine model, poses and screen on every given point, robust to decoding outliers.

    Converges first on an even subset (at most `subset_points` per pose), then drops
    outliers and polishes on all points; the covariance comes from the last normal matrix.
    """
    with single_thread_blas():  # small products: threads only contend
        return _fit_dense(model, poses, points, screen, free, outlier_rounds, max_iter, tol,
                          subset_points, progress or (lambda _msg: None))


def _fit_dense(model: PinholeFamily, poses: list[PoseEstimate], points: list[PointSet],
               screen: ScreenModel, free: np.ndarray, outlier_rounds: int, max_iter: int,
               tol: float, subset_points: int, report: Callable[[str], None]) -> DenseFit:
    """`fit_dense` under a single-threaded BLAS."""
    stride = max(1, -(-max(len(p) for p in points) // subset_points))
    prob = _Problem(model, poses, [p.subset(slice(None, None, stride)) for p in points],
                    screen, free)
    report(f"subset: {sum(len(p) for p in prob.points)} points")
    _, iters, converged = _levenberg_marquardt(prob, max_iter, tol, report)
    prob.set_points(points)
    keep = _outliers(prob.evaluate(False)[1])
    dropped = int(sum((~k).sum() for k in keep))
    for rnd in range(outlier_rounds + 1):
        prob.set_points([p.subset(k) for p, k in zip(prob.points, keep, strict=True)])
        report(f"all points, round {rnd + 1}: {sum(len(p) for p in prob.points)} points")
        state, n_it, converged = _levenberg_marquardt(prob, max_iter, tol, report)
        iters += n_it
        keep = _outliers(state[1])
        if rnd == outlier_rounds or all(k.all() for k in keep):
            break
        dropped += int(sum((~k).sum() for k in keep))
    cost, residuals, hmat, _ = state
    nres = int(sum(np.isfinite(r).sum() for r in residuals))
    chi2 = cost / max(nres - hmat.shape[0], 1)
    scale = np.sqrt(np.maximum(np.diag(hmat), 1e-300))
    try:
        cov = np.linalg.inv(hmat / np.outer(scale, scale)) / np.outer(scale, scale) * chi2
        var = np.diag(cov)
    except np.linalg.LinAlgError:
        var = np.full(hmat.shape[0], np.inf)
    ni, ns, _ = prob.sizes
    std = np.zeros(model.get_params().size)
    std[prob.free] = np.sqrt(np.clip(var[:ni], 0, None))
    stats = {"reduced_chi2": chi2, "iterations": iters, "converged": converged,
             "points": nres // 2, "dropped_outliers": dropped, "subset_stride": stride,
             "pose_std": [np.sqrt(np.clip(var[ni + ns + 6 * j:ni + ns + 6 * j + 6], 0, None)
                                  ).tolist() for j in range(len(prob.poses))]}
    return DenseFit(prob.model, prob.poses, prob.screen, prob.points, std,
                    np.sqrt(np.clip(var[ni:ni + ns], 0, None)), stats,
                    np.asarray(free, dtype=bool).copy())


def squared_norms(fit: DenseFit, points: list[PointSet]) -> list[np.ndarray]:
    """Per pose of `points`: each point's whitened squared residual (N,) at the fit's state,
    NaN where its ray misses or the fit's outlier rule (`fit_dense`) would drop it."""
    prob = _Problem(fit.model, fit.poses, points, fit.screen, np.zeros_like(fit.free))
    residuals = prob.evaluate(False)[1]
    out = []
    for r, keep in zip(residuals, _outliers(residuals), strict=True):
        sq = r[0::2] ** 2 + r[1::2] ** 2
        out.append(np.where(keep, sq, np.nan))
    return out


def flat_equivalent(fit: DenseFit, points: list[PointSet], poses: list[PoseEstimate] | None = None
                    ) -> list[PointSet]:
    """Decoded points moved to where a flat, bare screen would show them (for flat-screen stats).

    Per pixel: (ray meets plane z = 0) - (ray meets the fitted panel), added to the decoded
    point; with a flat screen the points come back unchanged.
    """
    if fit.screen.mode == "flat":
        return points
    flat = ScreenModel(fit.screen.geometry)
    out = []
    for pts, pose in zip(points, poses or fit.poses, strict=True):
        dirs, _, _ = directions(fit.model, pts.pixels, None, False)
        d = dirs @ pose.rotation
        o = np.broadcast_to(-(pose.rotation.T @ pose.translation), d.shape)
        q = d[:, :2] / d[:, 2:3]
        shift = (flat.trace(o, q, False)[0] - fit.screen.trace(o, q, False)[0]) / np.asarray(
            pts.pitch_mm)
        moved = pts.screen_px + np.where(np.isfinite(shift), shift, 0.0)
        out.append(PointSet(pts.pixels, moved, pts.sigma_px, pts.pitch_mm))
    return out
