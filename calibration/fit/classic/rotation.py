"""Self-calibration from conjugate rotations H = K R K^-1 (Hartley): pan-tilt rigs.

Between two views of a camera that only rotates about its centre of projection, the
image-to-image map is the infinite homography H = K R K^-1; scaled to det H = 1 it
satisfies H C H^T = C, linear in the six entries of C = K K^T; K follows by Cholesky.
Here the H come from a fixed plane's homographies (G_k G_0^-1). The general-motion
method (`classic.selfcal`) reaches the same linear step through vanishing points instead;
when the camera also translates, plane homographies are not conjugate rotations and this
method is wrong by tens of percent (benchmarks/RESULTS.md).
"""

from __future__ import annotations

import numpy as np

from calibration.fit.classic.estimate import IntrinsicsEstimate, normalizer
from calibration.fit.ransac import DegenerateError

_SYM = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


class NotPositiveDefiniteError(DegenerateError):
    """The estimated K K^T is not positive definite: no real K (too noisy or degenerate data)."""


def interview_homographies(plane_homographies: list[np.ndarray]) -> list[np.ndarray]:
    """Image-0 -> image-k maps G_k G_0^-1 from each view's plane-to-image homography G_k."""
    g0inv = np.linalg.inv(plane_homographies[0])
    return [g @ g0inv for g in plane_homographies[1:]]


def kkt_from_homographies(homographies: list[np.ndarray]) -> np.ndarray:
    """C = K K^T (C[2,2] = 1) solving H C H^T = C (H scaled to det 1) in least squares."""
    rows = []
    for h in homographies:
        det = np.linalg.det(h)
        if det == 0:
            raise DegenerateError("self-calibration: a singular inter-image homography")
        h = h / np.cbrt(det)
        for i, j in _SYM:
            row = np.zeros(6)
            for k, (a, b) in enumerate(_SYM):
                row[k] += h[i, a] * h[j, b] + (h[i, b] * h[j, a] if a != b else 0.0)
            row[_SYM.index((i, j))] -= 1.0
            rows.append(row)
    _, sv, vt = np.linalg.svd(np.array(rows))
    if sv[-2] < 1e-9 * sv[0]:
        raise DegenerateError("self-calibration: rotations about one axis only do not "
                              "determine K")
    c = np.zeros((3, 3))
    for k, (a, b) in enumerate(_SYM):
        c[a, b] = c[b, a] = vt[-1][k]
    return c / c[2, 2]


def k_from_kkt(c: np.ndarray) -> np.ndarray:
    """Upper-triangular K with K[2,2] = 1 and K K^T = C, by Cholesky of the flipped matrix."""
    flip = np.eye(3)[::-1]
    try:
        low = np.linalg.cholesky(flip @ c @ flip)
    except np.linalg.LinAlgError:
        raise NotPositiveDefiniteError(
            "self-calibration: K K^T is not positive definite (too noisy, too few images or "
            "too small rotations; for a camera that also moves use selfcal)") from None
    k = flip @ low @ flip
    return k / k[2, 2]


def rotation_intrinsics(homographies: list[np.ndarray]) -> np.ndarray:
    """K (with skew, K[2,2] = 1) from >= 2 inter-image homographies H = K R K^-1 (any scale)."""
    if len(homographies) < 2:
        raise DegenerateError(f"rotation self-calibration needs >= 2 inter-image homographies "
                              f"(3 images), got {len(homographies)}")
    return k_from_kkt(kkt_from_homographies(homographies))


def rotation_estimate(homographies: list[np.ndarray], image_size: tuple[int, int]
                      ) -> IntrinsicsEstimate:
    """`rotation_intrinsics` of image-0 -> image-k pixel homographies, solved in normalized
    image coordinates (better conditioned)."""
    t = normalizer(image_size)
    tinv = np.linalg.inv(t)
    k = tinv @ rotation_intrinsics([t @ h @ tinv for h in homographies])
    return IntrinsicsEstimate(k / k[2, 2], "rotation", len(homographies) + 1)
