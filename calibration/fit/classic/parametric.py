"""OpenCV-family fits (opencv5, opencv-rational, fisheye) from decoded point sets.

Each pose is subsampled evenly over the image (best-sigma pixel per cell); OpenCV's
solver runs single-threaded for repeatable results; points beyond 5 robust sigmas of the
first fit (decoding outliers) are dropped and the fit repeated. Per-parameter standard
deviations come from the weighted Gauss-Newton covariance (numerical Jacobian over
model and pose parameters, weights from the decoded sigmas).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import cv2
import numpy as np

from calibration.evaluate import pose_residuals, screen_jacobian
from calibration.fit.classic.options import MIN_POSES, ParametricOptions
from calibration.fit.correspondences import PointSet, subsample
from calibration.fit.ransac import DegenerateError
from calibration.fit.result import PoseEstimate
from calibration.models.parametric import PARAMETRIC_MODELS, PinholeFamily
from calibration.shared.progress import ProgressFn

# A fit whose fx (or cx, relative to the image width) is this uncertain is degenerate.
_MAX_REL_STD = 0.01


def _cv_points(points: list[PointSet]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """float32 object/image point lists in the layout cv2.calibrateCamera wants."""
    obj = [p.screen_mm.astype(np.float32).reshape(-1, 1, 3) for p in points]
    img = [p.pixels.astype(np.float32).reshape(-1, 1, 2) for p in points]
    return obj, img


def _run_opencv(name: str, points: list[PointSet], image_size: tuple[int, int],
                guess: np.ndarray | None, options: dict[str, Any]):
    """One OpenCV calibration; returns (K, distortion, rvecs, tvecs)."""
    obj, img = _cv_points(points)
    if name == "fisheye":
        flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
        k0 = np.zeros((3, 3)) if guess is None else guess.copy()
        if guess is not None:
            flags |= cv2.CALIB_USE_INTRINSIC_GUESS
        crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
        _, k, d, rv, tv = cv2.fisheye.calibrate(
            [o.reshape(1, -1, 3).astype(np.float64) for o in obj],
            [i.reshape(1, -1, 2).astype(np.float64) for i in img],
            image_size, k0, np.zeros(4), flags=flags, criteria=crit)
        return k, np.asarray(d).ravel(), rv, tv
    flags = 0
    if name == "opencv-rational":
        flags |= cv2.CALIB_RATIONAL_MODEL
        if options["thin_prism"]:
            flags |= cv2.CALIB_THIN_PRISM_MODEL
    if guess is not None:
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    _, k, d, rv, tv = cv2.calibrateCamera(obj, img, image_size, guess, None, flags=flags,
                                          criteria=crit)
    # OpenCV returns 5, 8, 12 or 14 (tilted sensor) coefficients; keep the model's own.
    return k, np.asarray(d).ravel()[: PARAMETRIC_MODELS[name].n_dist], rv, tv


def _poses(rvecs, tvecs) -> list[PoseEstimate]:
    """OpenCV rvec/tvec pairs as PoseEstimates (X_cam = R S + t)."""
    return [PoseEstimate(cv2.Rodrigues(np.asarray(r, dtype=np.float64).reshape(3))[0],
                         np.asarray(t, dtype=np.float64).ravel()) for r, t in zip(rvecs, tvecs,
                                                                                   strict=True)]


def param_std(model: PinholeFamily, poses: list[PoseEstimate], points: list[PointSet],
              fixed: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-parameter 1-sigma of the model (not the poses) from the weighted normal equations.

    Residuals are whitened by the expected camera-px sigma of each point and the
    covariance is scaled by the reduced chi-square; `fixed` marks unfitted parameters.
    """
    base = model.get_params()
    free = np.flatnonzero(~fixed)
    rows_w, jm_blocks, res_all = [], [], []
    for pose, pts in zip(poses, points, strict=True):
        jac = screen_jacobian(model, pose.rotation, pose.translation, pts)
        sig = np.sqrt(0.5 * np.einsum("nij,nj,nij->n", jac, pts.sigma_px**2, jac))
        rows_w.append(np.repeat(1.0 / sig, 2))
        res_all.append((_proj(model, pose, pts) - pts.pixels).ravel())
        cols = []
        for i in free:
            step = 1e-6 * max(abs(base[i]), 1e-3)
            v = base.copy()
            v[i] += step
            model.set_params(v)
            plus = _proj(model, pose, pts)
            v[i] -= 2 * step
            model.set_params(v)
            cols.append(((plus - _proj(model, pose, pts)) / (2 * step)).ravel())
            model.set_params(base)
        jm_blocks.append(np.stack(cols, axis=1))
    npar, nposes = free.size, len(poses)
    w = np.concatenate(rows_w)
    res = np.concatenate(res_all) * w
    jfull = np.zeros((res.size, npar + 6 * nposes))
    row = 0
    for j, (pose, pts, jm) in enumerate(zip(poses, points, jm_blocks, strict=True)):
        n2 = 2 * len(pts)
        jfull[row:row + n2, :npar] = jm
        jfull[row:row + n2, npar + 6 * j:npar + 6 * j + 6] = _pose_jac(model, pose, pts)
        row += n2
    jfull *= w[:, None]
    ok = np.isfinite(res) & np.all(np.isfinite(jfull), axis=1)
    jfull, res = jfull[ok], res[ok]
    chi2 = float(res @ res) / max(res.size - jfull.shape[1], 1)
    scale = np.linalg.norm(jfull, axis=0)
    scale[scale == 0] = 1.0
    jn = jfull / scale
    try:
        cov = np.linalg.inv(jn.T @ jn) / np.outer(scale, scale) * chi2
    except np.linalg.LinAlgError:
        cov = np.full((jfull.shape[1],) * 2, np.inf)
    std = np.zeros(base.size)
    std[free] = np.sqrt(np.clip(np.diag(cov)[:npar], 0, None))
    return std, chi2


def _proj(model: PinholeFamily, pose: PoseEstimate, pts: PointSet) -> np.ndarray:
    """Projected pixels of a pose's screen points."""
    return model.project(pts.screen_mm @ pose.rotation.T + pose.translation)


def _pose_jac(model: PinholeFamily, pose: PoseEstimate, pts: PointSet) -> np.ndarray:
    """(2N, 6) Jacobian of the projections w.r.t. the pose's rotation vector and translation."""
    rvec = cv2.Rodrigues(pose.rotation)[0].ravel()
    cols = []
    for i in range(6):
        out = []
        for sgn in (1.0, -1.0):
            r, t = rvec.copy(), pose.translation.copy()
            if i < 3:
                r[i] += sgn * 1e-7
            else:
                t[i - 3] += sgn * 1e-6 * max(float(np.linalg.norm(t)), 1.0)
            out.append(_proj(model, PoseEstimate(cv2.Rodrigues(r)[0], t), pts))
        step = 2e-7 if i < 3 else 2e-6 * max(float(np.linalg.norm(pose.translation)), 1.0)
        cols.append(((out[0] - out[1]) / step).ravel())
    return np.stack(cols, axis=1)


_SINGLE_THREAD_LOCK = threading.Lock()


@contextmanager
def _opencv_single_threaded() -> Iterator[None]:
    """Run OpenCV's solver on one thread (repeatable results, docs/calibration.md step 3).

    `cv2.setNumThreads` is process-wide, so concurrent fits in one process take turns
    here instead of resetting each other's thread count mid-solve.
    """
    with _SINGLE_THREAD_LOCK:
        prev = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            yield
        finally:
            cv2.setNumThreads(prev)


def fit_parametric(
    points: list[PointSet], image_size: tuple[int, int], model_name: str,
    options: ParametricOptions | None = None,
    progress: ProgressFn | None = None,
) -> tuple[PinholeFamily, list[PoseEstimate], list[PointSet], dict[str, Any]]:
    """Fit one OpenCV-family model; returns (model, poses, used point sets, fit stats)."""
    if model_name not in PARAMETRIC_MODELS:
        raise ValueError(f"model: expected one of {sorted(PARAMETRIC_MODELS)}, got {model_name!r}")
    opts = (options or ParametricOptions()).model_dump()
    if len(points) < MIN_POSES:
        raise DegenerateError(f"{model_name}: needs >= {MIN_POSES} poses, got {len(points)}")
    used = [subsample(p, int(opts["max_points_per_pose"])) for p in points]
    rounds = int(opts["outlier_rounds"])
    with _opencv_single_threaded():
        # OpenCV's planar (Zhang-style) init is robust for the pinhole models; the fisheye
        # solver's own init is not, so it starts from a rational fit (same f at the center).
        guess = None
        if model_name == "fisheye":
            guess = _run_opencv("opencv-rational", used, image_size, None, opts)[0]
        for rnd in range(rounds + 1):
            if progress:
                progress(rnd, rounds + 1, f"{model_name}: OpenCV fit round {rnd + 1}")
            try:
                k, d, rv, tv = _run_opencv(model_name, used, image_size, guess, opts)
            except cv2.error as exc:
                raise DegenerateError(
                    f"{model_name}: OpenCV calibration failed ({exc.err})") from None
            model = PARAMETRIC_MODELS[model_name](image_size, k, d)
            poses = _poses(rv, tv)
            if rnd == rounds:
                break
            keep = [pose_residuals(model, pose, p)["inliers"] for pose, p in zip(poses, used,
                                                                                  strict=True)]
            if all(k_.all() for k_ in keep):
                break
            used = [p.subset(k_) for p, k_ in zip(used, keep, strict=True)]
    fixed = np.zeros(model.get_params().size, dtype=bool)
    if model_name == "opencv-rational" and not opts["thin_prism"]:
        fixed[4 + 8:] = True
    std, chi2 = param_std(model, poses, used, fixed)
    w = float(image_size[0])
    if not (std[0] < _MAX_REL_STD * model.fx and std[2] < _MAX_REL_STD * w):
        raise DegenerateError(
            f"{model_name}: focal length / principal point not determined by these views "
            f"(fx = {model.fx:.1f} +- {std[0]:.3g} px, cx = {model.cx:.1f} +- {std[2]:.3g} px); "
            "the poses are too similar: add views tilted in different directions")
    stats = {"param_std": dict(zip(model.param_names(), std.tolist(), strict=True)),
             "reduced_chi2": chi2, "iterations": rnd + 1, "converged": True,
             "options": opts}
    return model, poses, used, stats
