"""Fit a parametric camera to target observations in pixel space.

Residual of target point i in view j: the model's projection of the point (seen from the
view's pose) minus the observed pixel, times weight_i / sigma_j (the file's `sigma_px`, or
one sigma estimated from the residuals of the views that give none): the maximum-likelihood
fit for independent Gaussian corner noise. OpenCV initializes (Zhang's method, or a guessed
K for non-planar points); scipy's Levenberg-Marquardt refines intrinsics, poses and, with
`target="fit"`, a bow of the target. Outliers (beyond `outlier_sigma` robust sigmas) are
dropped and the fit repeated until the set is stable. The covariance is the inverse normal
matrix at the solution; the intrinsics' block (poses marginalized) gives each pixel's
projection uncertainty.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np
from scipy.optimize import least_squares

from calibration.evaluate import ADEQUATE_RATIO
from calibration.fit.result import CalibrationResult, PoseEstimate
from calibration.fit.sparse.options import MIN_VIEWS, ObservationOptions
from calibration.fit.sparse.projection import project_view
from calibration.fit.sparse.target_shape import TargetShape
from calibration.models.base import CameraModel
from calibration.models.parametric import PARAMETRIC_MODELS, PinholeFamily
from calibration.shared.observations import TargetObservations

MIN_POINTS_PER_VIEW = 6  # a pose (6 unknowns) plus redundancy
_CHI_MEDIAN_2DOF = float(np.sqrt(2 * np.log(2)))  # median |r| of a whitened 2D Gaussian


class ObservationFitError(ValueError):
    """Observations a fit cannot use; the message names the view and why."""


@dataclass
class View:
    """One view's used points and its state in the fit (any model's pixel-space fit)."""

    index: int
    obs: TargetObservations
    rows: np.ndarray  # file rows of the used points
    xy: np.ndarray  # (n, 2) observed pixels
    xyz: np.ndarray  # (n, 3) target points
    weight: np.ndarray  # (n,)
    sigma: float  # pixel sigma of weight 1
    sigma_given: bool
    rvec: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tvec: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inlier: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))


@dataclass
class SparseFit:
    """The fitted camera, poses, target shape and uncertainty of a pixel-space fit."""

    model: CameraModel  # a PinholeFamily, or an sGCC model (calibration/fit/sparse/sgcc.py)
    poses: list[PoseEstimate]
    shape: TargetShape
    intrinsics_covariance: np.ndarray  # (P, P) over all of `get_params()`, 0 where fixed
    free: np.ndarray  # (P,) bool: intrinsics fitted
    stats: dict[str, Any]


def collect_views(observations: list[TargetObservations], weights: str) -> list[View]:
    """Used points of each view; errors name the view."""
    if not observations:
        raise ObservationFitError("observations: no views given")
    sizes = {tuple(o.image_size) for o in observations}
    if len(sizes) != 1:
        listing = ", ".join(f"view {i}: {o.image_size[0]}x{o.image_size[1]}"
                            for i, o in enumerate(observations))
        raise ObservationFitError(f"observations: image sizes differ ({listing})")
    out = []
    for i, obs in enumerate(observations):
        used = obs.used()
        if used.sum() < MIN_POINTS_PER_VIEW:
            raise ObservationFitError(
                f"observations: view {i} ({obs.meta.get('view', '?')}) has {int(used.sum())} "
                f"usable points (need >= {MIN_POINTS_PER_VIEW})")
        rows = np.flatnonzero(used)
        w = np.ones(rows.size) if weights == "equal" else obs.weights()[rows]
        out.append(View(i, obs, rows, obs.image_xy[rows], obs.target_xyz[rows], w,
                         obs.sigma_px or 1.0, obs.sigma_px is not None,
                         inlier=np.ones(rows.size, bool)))
    return out


def _opencv_flags(model_name: str, options: ObservationOptions) -> int:
    if model_name == "opencv-rational":
        return cv2.CALIB_RATIONAL_MODEL | (cv2.CALIB_THIN_PRISM_MODEL if options.thin_prism
                                           else 0)
    if model_name == "fisheye":  # started as a pinhole without distortion
        return (cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
                | cv2.CALIB_ZERO_TANGENT_DIST)
    return 0


def _initialize(views: list[View], size: tuple[int, int], model_name: str,
                options: ObservationOptions) -> PinholeFamily:
    """OpenCV's calibration as the start: Zhang's method for a planar target, a guessed K
    (focal = image width, centre) otherwise; sets each view's pose."""
    obj = [v.xyz.astype(np.float32).reshape(-1, 1, 3) for v in views]
    img = [v.xy.astype(np.float32).reshape(-1, 1, 2) for v in views]
    flags = _opencv_flags(model_name, options)
    k0 = None
    if any(np.any(v.xyz[:, 2] != 0) for v in views):
        w, h = size
        k0 = np.array([[w, 0, (w - 1) / 2], [0, w, (h - 1) / 2], [0, 0, 1]], np.float64)
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    try:
        _, k, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, k0, None, flags=flags)
    except cv2.error as exc:
        raise ObservationFitError(f"observations: OpenCV's initial calibration failed "
                                  f"({str(exc).strip().splitlines()[-1]})") from None
    cls = PARAMETRIC_MODELS[model_name]
    model = cls(size, k, None if model_name == "fisheye" else np.ravel(dist)[:cls.n_dist])
    for v, rv, tv in zip(views, rvecs, tvecs, strict=True):
        v.rvec, v.tvec = np.ravel(rv).astype(float), np.ravel(tv).astype(float)
    return model


def _free_intrinsics(model: PinholeFamily, options: ObservationOptions) -> np.ndarray:
    free = np.ones(model.get_params().size, dtype=bool)
    if model.type_name == "opencv-rational" and not options.thin_prism:
        free[4 + 8:] = False
    return free


class _Problem:  # a SparseProblem
    """Parameter vector [free intrinsics, target shape, (rvec, tvec) per view] over the
    inliers of every view; whitened residuals and their Jacobian."""

    def __init__(self, model: PinholeFamily, views: list[View], shape: TargetShape,
                 free: np.ndarray) -> None:
        self.model, self.views, self.shape = model, views, shape
        self.free = np.flatnonzero(free)
        self.ni, self.ns = self.free.size, shape.n_free

    def pack(self) -> np.ndarray:
        return np.concatenate([self.model.get_params()[self.free], self.shape.params,
                               *[np.concatenate([v.rvec, v.tvec]) for v in self.views]])

    def unpack(self, x: np.ndarray) -> None:
        p = self.model.get_params()
        p[self.free] = x[:self.ni]
        self.model.set_params(p)
        self.shape.params = x[self.ni:self.ni + self.ns].copy()
        for j, v in enumerate(self.views):
            o = self.ni + self.ns + 6 * j
            v.rvec, v.tvec = x[o:o + 3].copy(), x[o + 3:o + 6].copy()

    def evaluate(self, x: np.ndarray, want_jac: bool, all_points: bool = False
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        """Whitened residuals (inliers, or every used point) and, if asked, the Jacobian."""
        self.unpack(x)
        res, jacs = [], []
        n = x.size
        for j, v in enumerate(self.views):
            keep = slice(None) if all_points else v.inlier
            xyz, xy, w = v.xyz[keep], v.xy[keep], v.weight[keep]
            pts, d_shape = self.shape.points(xyz)
            proj = project_view(self.model, v.rvec, v.tvec, pts)
            s = (w / v.sigma)[:, None]
            res.append(((proj.pixels - xy) * s).ravel())
            if want_jac:
                jac = np.zeros((xyz.shape[0], 2, n))
                jac[:, :, :self.ni] = proj.d_intrinsics[:, :, self.free]
                if self.ns:
                    jac[:, :, self.ni:self.ni + self.ns] = np.einsum(
                        "nik,nks->nis", proj.d_point, d_shape)
                o = self.ni + self.ns + 6 * j
                jac[:, :, o:o + 6] = proj.d_pose
                jacs.append((jac * s[:, :, None]).reshape(-1, n))
        return np.concatenate(res), (np.concatenate(jacs) if want_jac else None)


def solve(problem: SparseProblem, max_nfev: int) -> Any:
    cache: dict[bytes, np.ndarray] = {}

    def fun(x: np.ndarray) -> np.ndarray:
        r, jac = problem.evaluate(x, True)
        cache.clear()
        cache[x.tobytes()] = jac
        return r

    def jac(x: np.ndarray) -> np.ndarray:
        hit = cache.get(x.tobytes())
        return hit if hit is not None else problem.evaluate(x, True)[1]

    sol = least_squares(fun, problem.pack(), jac=jac, method="lm", x_scale="jac",
                        ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=max_nfev)
    problem.unpack(sol.x)
    return sol


class SparseProblem(Protocol):
    """What the shared robust loop needs of a pixel-space problem (parametric or sGCC):
    its views, the parameter vector, and whitened residuals (the data's 2 per used point
    first, view by view; any prior rows after them) with their Jacobian."""

    views: list[View]

    def pack(self) -> np.ndarray: ...

    def unpack(self, x: np.ndarray) -> None: ...

    def evaluate(self, x: np.ndarray, want_jac: bool, all_points: bool = False
                 ) -> tuple[np.ndarray, np.ndarray | None]: ...


def view_residuals(problem: SparseProblem) -> list[np.ndarray]:
    """Per view, the pixel residual (n, 2) of every used point (model minus observed)."""
    r, _ = problem.evaluate(problem.pack(), False, all_points=True)
    out, start = [], 0
    for v in problem.views:
        n = v.rows.size
        out.append(r[start:start + 2 * n].reshape(n, 2) * (v.sigma / v.weight)[:, None])
        start += 2 * n
    return out


def _view_norms(problem: SparseProblem) -> list[np.ndarray]:
    """Per view, the whitened residual norm of every used point."""
    return [np.hypot(d[:, 0], d[:, 1]) * v.weight / v.sigma
            for v, d in zip(problem.views, view_residuals(problem), strict=True)]


def fitted_parameters(problem: SparseProblem, n_data: int) -> float:
    """How many parameters the data fix: trace(J_d^T J_d (J^T J)^-1), J_d the first `n_data`
    (data) rows of the Jacobian. Every parameter when there is no prior; fewer where prior
    rows (the sGCC spline's) define what no point reaches, so they do not eat into the
    degrees of freedom that sigma is estimated with."""
    _, jac = problem.evaluate(problem.pack(), True)
    if jac.shape[0] == n_data:
        return float(jac.shape[1])
    normal = jac.T @ jac
    scale = np.sqrt(np.clip(np.diag(normal), 1e-300, None))
    data = jac[:n_data] / scale
    try:
        return float(np.trace(np.linalg.solve(normal / np.outer(scale, scale), data.T @ data)))
    except np.linalg.LinAlgError:
        return float(jac.shape[1])


def _update_sigma(problem: SparseProblem) -> None:
    """One sigma for the views whose files give none: from their inlier residuals, with the
    fit's degrees of freedom shared out by point count."""
    unknown = [v for v in problem.views if not v.sigma_given]
    if not unknown:
        return
    norms = _view_norms(problem)
    m_all = sum(2 * int(v.inlier.sum()) for v in problem.views)
    n_par = fitted_parameters(problem, m_all)
    ss, m = 0.0, 0
    for v, nr in zip(problem.views, norms, strict=True):
        if not v.sigma_given:
            ss += float(np.sum((nr[v.inlier] * v.sigma) ** 2))
            m += 2 * int(v.inlier.sum())
    dof = m - n_par * m / m_all
    if dof <= 0:
        raise ObservationFitError(f"observations: {m} residuals cannot fix {n_par:.0f} "
                                  "unknowns")
    sigma = float(np.sqrt(ss / dof))
    for v in unknown:
        v.sigma = sigma


def _flag_outliers(problem: SparseProblem, k: float) -> bool:
    """Mark points beyond k robust sigmas; True if the inlier set changed."""
    norms = _view_norms(problem)
    scale = float(np.median(np.concatenate(norms))) / _CHI_MEDIAN_2DOF
    changed = False
    for v, nr in zip(problem.views, norms, strict=True):
        inl = nr <= k * scale
        if inl.sum() < MIN_POINTS_PER_VIEW:  # keep the best points rather than lose the view
            inl = nr <= np.sort(nr)[MIN_POINTS_PER_VIEW - 1]
        changed |= not np.array_equal(inl, v.inlier)
        v.inlier = inl
    return changed


def robust_fit(problem: SparseProblem, opts: ObservationOptions, label: str,
               progress: Callable[[int, int, str], None] | None = None
               ) -> tuple[int, int, bool]:
    """Solve, estimate the sigma of views that give none, solve again, drop outliers beyond
    `outlier_sigma` robust sigmas and repeat until the inlier set is stable (at most
    `outlier_rounds` refits): (evaluations, rounds, converged)."""
    nfev, rounds, converged = 0, 0, False
    for rounds in range(opts.outlier_rounds + 1):
        if progress is not None:
            progress(rounds, opts.outlier_rounds + 1, f"{label}: pixel-space fit")
        nfev += solve(problem, opts.max_iterations).nfev
        _update_sigma(problem)  # the weights change only where views give no sigma
        sol = solve(problem, opts.max_iterations)
        nfev += sol.nfev
        converged = bool(sol.success)
        if rounds == opts.outlier_rounds or not _flag_outliers(problem, opts.outlier_sigma):
            break
    return nfev, rounds, converged


def covariance_of(problem: SparseProblem) -> np.ndarray:
    """Inverse normal matrix of every parameter at the solution (Jacobi-scaled inverse)."""
    _, jac = problem.evaluate(problem.pack(), True)
    normal = jac.T @ jac
    scale = np.sqrt(np.clip(np.diag(normal), 1e-300, None))
    try:
        inv = np.linalg.inv(normal / np.outer(scale, scale))
    except np.linalg.LinAlgError:
        raise ObservationFitError("observations: the fit is degenerate (singular normal "
                                  "matrix): the views do not fix every parameter") from None
    return inv / np.outer(scale, scale)


def view_statistics(problem: SparseProblem, rotations: list[np.ndarray]
                    ) -> tuple[list[PoseEstimate], dict[str, Any]]:
    """Each view's pose (given its rotation matrix) and residual row, and the fit's RMS,
    expected RMS, chi^2 and outlier count: the statistics every pixel-space fit reports."""
    per_pose, poses, sq, count = [], [], 0.0, 0
    chi2, expected_sq = 0.0, 0.0
    for v, d, rot in zip(problem.views, view_residuals(problem), rotations, strict=True):
        e2 = np.sum(d * d, axis=1)[v.inlier]
        chi2 += float(np.sum(e2 * (v.weight[v.inlier] / v.sigma) ** 2))
        sq, count = sq + float(e2.sum()), count + int(v.inlier.sum())
        expected_sq += float(np.sum(2 * (v.sigma / v.weight[v.inlier]) ** 2))
        rms = float(np.sqrt(e2.mean()))
        per_pose.append({
            "view": str(v.obs.meta.get("view", v.index)), "source": v.obs.meta.get("source"),
            "rms_px": rms, "n_points": int(v.inlier.sum()), "sigma_px": v.sigma,
            "sigma_estimated": not v.sigma_given,
            "outliers": v.rows[~v.inlier].tolist(),
            "outlier_residuals_px": np.hypot(d[~v.inlier, 0], d[~v.inlier, 1]).tolist()})
        poses.append(PoseEstimate(rot, v.tvec.copy(), rms, None, int(v.inlier.sum())))
    rms, expected = float(np.sqrt(sq / count)), float(np.sqrt(expected_sq / count))
    stats: dict[str, Any] = {
        "source": "observations",
        "rms_px": rms,
        # with sigma estimated from these residuals the ratio is ~1 by construction; the
        # cross-validation is then the test of the model
        "expected_rms_px": expected,
        "noise_floor_ratio": rms / expected,
        "model_adequate": bool(rms / expected <= ADEQUATE_RATIO),
        "sigma_estimated": any(not v.sigma_given for v in problem.views),
        "sigma_px": float(np.median([v.sigma for v in problem.views])),
        "reduced_chi2_sum": chi2, "residual_count": 2 * count,
        "per_pose": per_pose,
        "outliers": int(sum((~v.inlier).sum() for v in problem.views)),
    }
    return poses, stats


def fit_observations(
    observations: list[TargetObservations], model_name: str,
    options: ObservationOptions | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> SparseFit:
    """Fit `model_name` (a parametric model) to the views; see the module docstring."""
    opts = options or ObservationOptions()
    if model_name not in PARAMETRIC_MODELS:
        raise ObservationFitError(f"model: {model_name!r} is not a parametric model")
    if len(observations) < MIN_VIEWS:
        raise ObservationFitError(f"observations: {model_name} needs >= {MIN_VIEWS} views, "
                                  f"got {len(observations)}")
    t0 = time.perf_counter()
    views = collect_views(observations, opts.weights)
    size = observations[0].image_size
    model = _initialize(views, size, model_name, opts)
    shape = TargetShape.of(np.concatenate([v.xyz for v in views]), opts.target)
    free = _free_intrinsics(model, opts)
    problem = _Problem(model, views, shape, free)
    nfev, rounds, converged = robust_fit(problem, opts, model_name, progress)
    cov = covariance_of(problem)
    return _summarize(problem, cov, free, opts, nfev, rounds, converged,
                      time.perf_counter() - t0)


def _summarize(problem: _Problem, cov: np.ndarray, free: np.ndarray,
               opts: ObservationOptions, nfev: int, rounds: int, converged: bool,
               wall_s: float) -> SparseFit:
    model, views, ni, ns = problem.model, problem.views, problem.ni, problem.ns
    p = model.get_params().size
    cov_int = np.zeros((p, p))
    cov_int[np.ix_(problem.free, problem.free)] = cov[:ni, :ni]
    problem.shape.set_covariance(cov[ni:ni + ns, ni:ni + ns])
    std = np.sqrt(np.clip(np.diag(cov_int), 0, None))
    poses, stats = view_statistics(problem, [cv2.Rodrigues(v.rvec)[0] for v in views])
    chi2, n_res = stats.pop("reduced_chi2_sum"), stats.pop("residual_count")
    names = model.param_names()
    stats.update({
        "reduced_chi2": chi2 / max(n_res - cov.shape[0], 1),
        "param_std": dict(zip(names, std.tolist(), strict=True)),
        "target": problem.shape.to_json(),
        "intrinsics_covariance": {"names": names, "matrix": cov_int.tolist()},
        "options": opts.model_dump(),
        "iterations": nfev, "outlier_rounds": rounds, "converged": converged,
        "training_poses": list(range(len(views))), "wall_s": wall_s,
    })
    return SparseFit(model, poses, problem.shape, cov_int, free, stats)


def to_result(fit: SparseFit) -> CalibrationResult:
    """The fit as every calibration returns it; the model carries its statistics."""
    keep = ("source", "rms_px", "expected_rms_px", "noise_floor_ratio", "model_adequate",
            "sigma_estimated", "sigma_px", "reduced_chi2", "param_std", "per_pose",
            "outliers", "target", "intrinsics_covariance", "projection_sigma_px")
    fit.model.stats = {k: fit.stats[k] for k in keep if k in fit.stats}
    return CalibrationResult(model=fit.model, poses=fit.poses, stats=fit.stats)
