"""Seed 003's classic estimators through OpenCV: PnP for any (non-)coplanar points, USAC
(MAGSAC++) homographies and PnP with adaptive termination, and an adaptive RANSAC for the
3x4 DLT, which OpenCV lacks.

Adaptive termination: after a model with inlier ratio w is found, N = log(1 - p) /
log(1 - w^s) samples suffice for confidence p with s-point samples; the loop stops there.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from calibration.fit.dlt import dlt_projection, project_with
from calibration.fit.homography import DegenerateError

PNP_METHODS = {"sqpnp": cv2.SOLVEPNP_SQPNP, "epnp": cv2.SOLVEPNP_EPNP,
               "iterative": cv2.SOLVEPNP_ITERATIVE}
_REFITS = 10


def _as_pairs(points: np.ndarray, pixels: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Validated float64 (N, dim) and (N, 2) arrays."""
    x = np.asarray(points, dtype=np.float64)
    u = np.asarray(pixels, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != dim or u.shape != (x.shape[0], 2):
        raise ValueError(f"expected (N, {dim}) points and (N, 2) pixels, got {x.shape}, {u.shape}")
    return x, u


def solve_pnp(
    points: np.ndarray, pixels: np.ndarray, k: np.ndarray, dist: np.ndarray | None = None, *,
    method: str = "sqpnp",
) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, RMS px) of the object from >= 4 3-D/2-D pairs (planar or not), LM-polished."""
    if method not in PNP_METHODS:
        raise ValueError(f"method: expected one of {sorted(PNP_METHODS)}, got {method!r}")
    x, u = _as_pairs(points, pixels, 3)
    if len(x) < (6 if method == "iterative" else 4):
        raise DegenerateError(f"PnP ({method}) needs more points, got {len(x)}")
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(x, u, k, d, flags=PNP_METHODS[method])
    if not ok:
        raise DegenerateError(f"PnP ({method}): no solution (degenerate point layout?)")
    rvec, tvec = cv2.solvePnPRefineLM(x, u, k, d, rvec, tvec)
    proj, _ = cv2.projectPoints(x, rvec, tvec, k, d)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - u) ** 2, axis=1))))
    return cv2.Rodrigues(rvec)[0], tvec.ravel(), rms


def _usac(threshold: float, confidence: float, max_iterations: int, seed: int) -> cv2.UsacParams:
    """MAGSAC++ settings with local optimization and adaptive termination."""
    p = cv2.UsacParams()
    p.threshold, p.confidence, p.maxIterations = threshold, confidence, max_iterations
    p.sampler, p.score = cv2.SAMPLING_UNIFORM, cv2.SCORE_METHOD_MAGSAC
    p.loMethod, p.randomGeneratorState = cv2.LOCAL_OPTIM_SIGMA, seed
    return p


def pnp_ransac(
    points: np.ndarray, pixels: np.ndarray, k: np.ndarray, dist: np.ndarray | None = None, *,
    threshold_px: float = 2.0, confidence: float = 0.999, max_iterations: int = 10000,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, t, inlier mask) by OpenCV's USAC PnP (MAGSAC++), then LM on the inliers."""
    x, u = _as_pairs(points, pixels, 3)
    if len(x) < 6:
        raise DegenerateError(f"PnP RANSAC needs >= 6 points, got {len(x)}")
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
    params = _usac(threshold_px, confidence, max_iterations, seed)
    ok, _, rvec, tvec, idx = cv2.solvePnPRansac(x, u, k.copy(), d, None, None, None, params)
    if not ok or idx is None or len(idx) < 6:
        raise DegenerateError("PnP RANSAC: no consensus set of >= 6 inliers")
    inl = np.zeros(len(x), dtype=bool)
    inl[np.asarray(idx).ravel()] = True
    rvec, tvec = cv2.solvePnPRefineLM(x[inl], u[inl], k, d, rvec, tvec)
    return cv2.Rodrigues(rvec)[0], tvec.ravel(), inl


def usac_homography(
    src: np.ndarray, dst: np.ndarray, threshold: float, *, confidence: float = 0.999,
    max_iterations: int = 10000, seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """(H with dst ~ H src, inlier mask) by OpenCV's USAC MAGSAC++ with adaptive termination."""
    s, d = _as_pairs(src, dst, 2)
    if len(s) < 4:
        raise DegenerateError(f"homography needs >= 4 points, got {len(s)}")
    h, mask = cv2.findHomography(s, d, _usac(threshold, confidence, max_iterations, seed))
    if h is None or mask is None or int(mask.sum()) < 4:
        raise DegenerateError("USAC homography: no consensus set of >= 4 inliers")
    return h / h[2, 2], mask.ravel().astype(bool)


def required_iterations(inlier_ratio: float, sample_size: int, confidence: float) -> float:
    """Samples needed to draw one all-inlier sample with probability `confidence`."""
    good = inlier_ratio**sample_size
    if good >= 1.0:
        return 1.0
    if good <= 0.0:
        return float("inf")
    return float(np.log(1 - confidence) / np.log1p(-good))


def adaptive_ransac(
    n: int, sample_size: int, fit: Callable[[np.ndarray], np.ndarray],
    errors: Callable[[np.ndarray], np.ndarray], threshold: float, rng: np.random.Generator, *,
    confidence: float = 0.999, max_iterations: int = 100000,
) -> tuple[np.ndarray, np.ndarray, int]:
    """(model refit on its consensus set, inlier mask, samples drawn); stops adaptively."""
    if n < sample_size:
        raise DegenerateError(f"RANSAC needs >= {sample_size} points, got {n}")
    best = np.zeros(n, dtype=bool)
    needed, drawn = float(max_iterations), 0
    while drawn < min(needed, max_iterations):
        drawn += 1
        try:
            model = fit(rng.choice(n, sample_size, replace=False))
        except DegenerateError:
            continue
        inl = errors(model) < threshold
        if inl.sum() > best.sum():
            best = inl
            needed = required_iterations(inl.mean(), sample_size, confidence)
    if best.sum() < sample_size:
        raise DegenerateError(f"RANSAC: no consensus set of >= {sample_size} inliers")
    inl = best
    for _ in range(_REFITS):  # refit on the consensus set until it is stable
        model = fit(np.flatnonzero(inl))
        new = errors(model) < threshold
        if new.sum() < sample_size or np.array_equal(new, inl):
            break
        inl = new
    return model, inl, drawn


def dlt_ransac(
    points: np.ndarray, pixels: np.ndarray, threshold_px: float, rng: np.random.Generator, *,
    confidence: float = 0.999,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Robust 3x4 P from non-coplanar points: (P, inlier mask, samples drawn)."""
    x, u = _as_pairs(points, pixels, 3)
    return adaptive_ransac(
        len(x), 6, lambda i: dlt_projection(x[i], u[i]),
        lambda p: np.linalg.norm(project_with(p, x) - u, axis=1), threshold_px, rng,
        confidence=confidence)
