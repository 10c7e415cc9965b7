"""Classic estimators through OpenCV: PnP for any (non-)coplanar points and
USAC (MAGSAC++ scoring, local optimization, adaptive termination) for homographies and PnP.
The 3x4 DLT, which OpenCV lacks, runs in the package's own adaptive RANSAC
(`classic.dlt.ransac_dlt`)."""

from __future__ import annotations

import cv2
import numpy as np

from calibration.fit.ransac import DegenerateError

PNP_METHODS = {"sqpnp": cv2.SOLVEPNP_SQPNP, "epnp": cv2.SOLVEPNP_EPNP,
               "iterative": cv2.SOLVEPNP_ITERATIVE}


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
