"""Plane-to-image homographies by the normalized DLT, with an optional RANSAC wrapper."""

from __future__ import annotations

import numpy as np

from calibration.fit.ransac import DegenerateError, ransac


def _normalizer(p: np.ndarray) -> np.ndarray:
    """Hartley normalization: centroid to 0, mean distance sqrt(2)."""
    c = p.mean(axis=0)
    s = np.sqrt(2) / max(float(np.mean(np.linalg.norm(p - c, axis=1))), 1e-300)
    return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])


def fit_homography(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """H (3x3, H[2,2]=1) with dst ~ H src from N >= 4 point pairs (N, 2), normalized DLT."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 2:
        raise ValueError(f"fit_homography: expected two (N, 2) arrays, got {src.shape} {dst.shape}")
    if src.shape[0] < 4:
        raise DegenerateError(f"homography needs >= 4 points, got {src.shape[0]}")
    ts, td = _normalizer(src), _normalizer(dst)
    s = src @ ts[:2, :2].T + ts[:2, 2]
    d = dst @ td[:2, :2].T + td[:2, 2]
    n = s.shape[0]
    one, zero = np.ones(n), np.zeros(n)
    sh = np.stack([s[:, 0], s[:, 1], one], axis=1)
    z3 = np.stack([zero, zero, zero], axis=1)
    a = np.empty((2 * n, 9))
    a[0::2] = np.hstack([sh, z3, -d[:, :1] * sh])
    a[1::2] = np.hstack([z3, sh, -d[:, 1:] * sh])
    if weights is not None:
        w = np.sqrt(np.asarray(weights, dtype=np.float64))
        a *= np.repeat(w, 2)[:, None]
    if a.shape[0] < 9:  # minimal case: pad so that the null vector is among the 9 of vt
        a = np.vstack([a, np.zeros((9 - a.shape[0], 9))])
    _, sv, vt = np.linalg.svd(a, full_matrices=False)
    if sv[-2] < 1e-9 * sv[0]:
        raise DegenerateError("homography: points are degenerate (collinear or repeated)")
    h = np.linalg.inv(td) @ vt[-1].reshape(3, 3) @ ts
    return h / h[2, 2]


def apply_homography(h: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Map (N, 2) points through H."""
    q = np.asarray(p, dtype=np.float64) @ h[:, :2].T + h[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return q[:, :2] / q[:, 2:]


def ransac_homography(
    src: np.ndarray, dst: np.ndarray, threshold: float, rng: np.random.Generator,
    *, iterations: int = 10000, confidence: float = 0.999,
    stats: dict[str, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Robust H: best 4-point model by inlier count (dst error < threshold), adaptive
    termination at `confidence`, refit on the inliers; (H, inlier mask)."""
    return ransac(
        src.shape[0], 4, lambda i: fit_homography(src[i], dst[i]),
        lambda h: np.linalg.norm(apply_homography(h, src) - dst, axis=1), threshold, rng,
        iterations=iterations, confidence=confidence, what="homography", stats=stats,
    )
