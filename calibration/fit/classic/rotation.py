"""Self-calibration of a camera that only rotates (seed 004, Hartley): K from H = K R K^-1.

Between two views of a purely rotating camera the image-to-image map is the infinite
homography H = K R K^-1; scaled to det H = 1 it satisfies H (K K^T) H^T = K K^T,
linear in the six entries of the symmetric matrix C = K K^T. K follows by Cholesky.
"""

from __future__ import annotations

import numpy as np

from calibration.fit.ransac import DegenerateError

_SYM = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


def interview_homographies(plane_homographies: list[np.ndarray]) -> list[np.ndarray]:
    """Image-0 -> image-k maps G_k G_0^-1 from each view's plane-to-image homography G_k."""
    g0inv = np.linalg.inv(plane_homographies[0])
    return [g @ g0inv for g in plane_homographies[1:]]


def rotation_intrinsics(homographies: list[np.ndarray]) -> np.ndarray:
    """K (upper triangular, K[2,2] = 1) from >= 2 inter-view homographies of a rotating camera."""
    if len(homographies) < 2:
        raise DegenerateError(
            f"rotation-only self-calibration needs >= 2 inter-view homographies (3 views), "
            f"got {len(homographies)}"
        )
    rows = []
    for h in homographies:
        h = h / np.cbrt(np.linalg.det(h))
        for i, j in _SYM:
            row = np.zeros(6)
            for k, (a, b) in enumerate(_SYM):
                coef = h[i, a] * h[j, b] + (h[i, b] * h[j, a] if a != b else 0.0)
                row[k] += coef
            row[_SYM.index((i, j))] -= 1.0
            rows.append(row)
    _, sv, vt = np.linalg.svd(np.array(rows))
    if sv[-2] < 1e-9 * sv[0]:
        raise DegenerateError("rotation-only: rotations about one axis do not determine K")
    c = np.zeros((3, 3))
    for k, (a, b) in enumerate(_SYM):
        c[a, b] = c[b, a] = vt[-1][k]
    c /= c[2, 2]
    # K K^T with K upper triangular: Cholesky of the flipped matrix, flipped back.
    flip = np.eye(3)[::-1]
    try:
        low = np.linalg.cholesky(flip @ c @ flip)
    except np.linalg.LinAlgError:
        raise DegenerateError("rotation-only: K K^T estimate is not positive definite") from None
    k = flip @ low @ flip
    return k / k[2, 2]
