"""Zhang's closed-form intrinsics from plane homographies (image ~ H [X, Y, 1])."""

from __future__ import annotations

import numpy as np

from calibration.fit.ransac import DegenerateError


def _v(h: np.ndarray, i: int, j: int) -> np.ndarray:
    """Row of Zhang's constraint h_i^T B h_j for the six entries of B = K^-T K^-1."""
    a, b = h[:, i], h[:, j]
    return np.array([a[0] * b[0], a[0] * b[1] + a[1] * b[0], a[1] * b[1],
                     a[2] * b[0] + a[0] * b[2], a[2] * b[1] + a[1] * b[2], a[2] * b[2]])


def zhang_intrinsics(homographies: list[np.ndarray]) -> np.ndarray:
    """K (3x3, zero skew) from >= 3 homographies of a plane seen in different orientations."""
    if len(homographies) < 3:
        raise DegenerateError(f"Zhang's method needs >= 3 views, got {len(homographies)}")
    rows = []
    for h in homographies:
        hn = h / np.linalg.norm(h[:, 0])
        rows += [_v(hn, 0, 1), _v(hn, 0, 0) - _v(hn, 1, 1)]
    rows.append(np.array([0, 1.0, 0, 0, 0, 0]))  # zero skew
    _, sv, vt = np.linalg.svd(np.array(rows))
    if sv[-2] < 1e-12 * sv[0]:
        raise DegenerateError("Zhang: views are degenerate (parallel planes or pure translation)")
    b11, b12, b22, b13, b23, b33 = vt[-1]
    v0 = (b12 * b13 - b11 * b23) / (b11 * b22 - b12 * b12)
    lam = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11
    if lam / b11 <= 0 or lam * b11 / (b11 * b22 - b12 * b12) <= 0:
        raise DegenerateError("Zhang: no positive-definite solution (views too similar or noisy)")
    alpha = np.sqrt(lam / b11)
    beta = np.sqrt(lam * b11 / (b11 * b22 - b12 * b12))
    u0 = -b13 * alpha * alpha / lam
    return np.array([[alpha, 0, u0], [0, beta, v0], [0, 0, 1.0]])


def pose_from_homography(k: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of the plane from H ~ K [r1 r2 t], R projected onto SO(3), plane in front."""
    m = np.linalg.solve(k, h)
    lam = 1.0 / np.linalg.norm(m[:, 0])
    if m[2, 2] * lam < 0:
        lam = -lam
    r1, r2, t = lam * m[:, 0], lam * m[:, 1], lam * m[:, 2]
    r = np.stack([r1, r2, np.cross(r1, r2)], axis=1)
    u, _, vt = np.linalg.svd(r)
    r = u @ vt
    if np.linalg.det(r) < 0:
        r = u @ np.diag([1, 1, -1.0]) @ vt
    return r, t
