"""Direct linear transform: 3x4 camera matrix from non-coplanar 3D-2D points, RANSAC."""

from __future__ import annotations

import numpy as np
import scipy.linalg

from calibration.fit.ransac import DegenerateError, ransac


def _normalizer(p: np.ndarray) -> np.ndarray:
    """Similarity moving the centroid to 0 and the mean distance to sqrt(dim)."""
    dim = p.shape[1]
    c = p.mean(axis=0)
    s = np.sqrt(dim) / max(float(np.mean(np.linalg.norm(p - c, axis=1))), 1e-300)
    t = np.eye(dim + 1) * s
    t[:dim, dim] = -s * c
    t[dim, dim] = 1.0
    return t


def dlt_projection(points: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """P (3x4, ||P|| = 1), pixels ~ P [X, 1], from N >= 6 non-coplanar points (normalized)."""
    x = np.asarray(points, dtype=np.float64)
    u = np.asarray(pixels, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or u.shape != (x.shape[0], 2):
        raise ValueError(f"dlt_projection: expected (N, 3) and (N, 2), got {x.shape}, {u.shape}")
    if x.shape[0] < 6:
        raise DegenerateError(f"DLT needs >= 6 points, got {x.shape[0]}")
    t3, t2 = _normalizer(x), _normalizer(u)
    xn = np.column_stack([x @ t3[:3, :3].T + t3[:3, 3], np.ones(len(x))])
    un = u @ t2[:2, :2].T + t2[:2, 2]
    z = np.zeros_like(xn)
    a = np.empty((2 * len(x), 12))
    a[0::2] = np.hstack([xn, z, -un[:, :1] * xn])
    a[1::2] = np.hstack([z, xn, -un[:, 1:] * xn])
    _, sv, vt = np.linalg.svd(a, full_matrices=False)
    if sv[-2] < 1e-9 * sv[0]:
        raise DegenerateError("DLT: points are degenerate (coplanar or collinear)")
    p = np.linalg.inv(t2) @ vt[-1].reshape(3, 4) @ t3
    return p / np.linalg.norm(p)


def project_with(p: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixels of (N, 3) points under a 3x4 camera matrix."""
    q = points @ p[:, :3].T + p[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return q[:, :2] / q[:, 2:]


def decompose_projection(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """P = K [R | t] by RQ decomposition: (K with K[2,2] = 1 and positive diagonal, R, t)."""
    m = p[:, :3]
    if np.linalg.det(m) < 0:
        p = -p
        m = p[:, :3]
    k, r = scipy.linalg.rq(m)
    s = np.diag(np.sign(np.diag(k)))
    k, r = k @ s, s @ r
    t = np.linalg.solve(k, p[:, 3])
    return k / k[2, 2], r, t


def ransac_dlt(
    points: np.ndarray, pixels: np.ndarray, threshold_px: float, rng: np.random.Generator,
    *, iterations: int = 10000, confidence: float = 0.999,
    stats: dict[str, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Robust DLT: best 6-point model by inlier count, adaptive termination at `confidence`,
    refit on all inliers; (P, inlier mask)."""
    return ransac(
        points.shape[0], 6, lambda i: dlt_projection(points[i], pixels[i]),
        lambda p: np.linalg.norm(project_with(p, points) - pixels, axis=1), threshold_px, rng,
        iterations=iterations, confidence=confidence, what="DLT", stats=stats,
    )
