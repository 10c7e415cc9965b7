"""Self-calibration from conjugate rotations H = K R K^-1: general motion (seed 004) and
rotation-only (pan-tilt) data share the last step.

General motion (Chang, Wang & Wang): the camera moves and rotates; vanishing points of
>= 4 world directions (the edge directions of two non-parallel rectangles, no three of
them coplanar) are tracked across images. Translation does not move vanishing points,
so the vanishing points of image i map to those of image j by the infinite homography
H_ij = K R_ij K^-1, fitted by DLT on the homogeneous points. Scaled to det H = 1 it
satisfies H C H^T = C with C = K K^T, linear in C's six entries; K by Cholesky. With
noisy vanishing points C can fail to be positive definite: a clear error, as the paper
warns. Rotation-only data give the same H directly as image-to-image homographies.
"""

from __future__ import annotations

import itertools

import numpy as np

from calibration.fit.estimate import IntrinsicsEstimate
from calibration.fit.homography import DegenerateError

_SYM = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]


class NotPositiveDefiniteError(DegenerateError):
    """The estimated K K^T is not positive definite: no real K (too noisy or degenerate data)."""


def homogeneous_homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """H with dst ~ H src from >= 4 homogeneous point pairs (N, 3), no three collinear.

    Cross-product DLT (x' x H x = 0), so points at infinity are fine; the points should be
    in normalized coordinates (see `conjugate_rotation_intrinsics`).
    """
    s = src / np.linalg.norm(src, axis=1, keepdims=True)
    d = dst / np.linalg.norm(dst, axis=1, keepdims=True)
    if len(s) < 4:
        raise DegenerateError(f"infinite homography needs >= 4 vanishing points, got {len(s)}")
    rows = []
    for x, y in zip(s, d, strict=True):
        z = np.zeros(3)
        rows += [np.concatenate([z, -y[2] * x, y[1] * x]),
                 np.concatenate([y[2] * x, z, -y[0] * x]),
                 np.concatenate([-y[1] * x, y[0] * x, z])]
    _, sv, vt = np.linalg.svd(np.array(rows))
    if sv[-2] < 1e-8 * sv[0]:
        raise DegenerateError("infinite homography: three of the directions are coplanar "
                              "(e.g. both rectangles share an edge direction)")
    return vt[-1].reshape(3, 3)


def kkt_from_homographies(homographies: list[np.ndarray]) -> np.ndarray:
    """C = K K^T (C[2,2] = 1) solving H C H^T = C (det H = 1) for >= 2 conjugate rotations."""
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
            "self-calibration: K K^T is not positive definite (vanishing points too noisy, "
            "too few images or too small rotations); add images or rotate more") from None
    k = flip @ low @ flip
    return k / k[2, 2]


def conjugate_rotation_intrinsics(homographies: list[np.ndarray]) -> np.ndarray:
    """K (with skew) from >= 2 image-to-image homographies H = K R K^-1 (any scale)."""
    if len(homographies) < 2:
        raise DegenerateError(f"self-calibration needs >= 2 inter-image homographies (3 "
                              f"images), got {len(homographies)}")
    return k_from_kkt(kkt_from_homographies(homographies))


def normalizer(image_size: tuple[int, int]) -> np.ndarray:
    """Pixel -> normalized coordinates (center to 0, (W + H) / 2 to 1)."""
    w, h = image_size
    s = 2.0 / (w + h)
    return np.array([[s, 0, -s * (w - 1) / 2], [0, s, -s * (h - 1) / 2], [0, 0, 1.0]])


def linear_selfcal(vps: np.ndarray, t: np.ndarray) -> np.ndarray:
    """K in pixels from (images, directions, 3) homogeneous pixel vanishing points."""
    vn = vps @ t.T
    hs = [homogeneous_homography(vn[i], vn[j])
          for i, j in itertools.combinations(range(len(vn)), 2)]
    k = np.linalg.inv(t) @ conjugate_rotation_intrinsics(hs)
    return k / k[2, 2]


def rotation_intrinsics_from_images(
    homographies: list[np.ndarray], image_size: tuple[int, int],
) -> IntrinsicsEstimate:
    """Rotation-only (pan-tilt rig, Hartley) K from image-0 -> image-k homographies in pixels."""
    t = normalizer(image_size)
    hn = [t @ h @ np.linalg.inv(t) for h in homographies]
    k = np.linalg.inv(t) @ conjugate_rotation_intrinsics(hn)
    return IntrinsicsEstimate(k / k[2, 2], "rotation", len(homographies) + 1)
