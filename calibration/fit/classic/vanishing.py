"""Intrinsics from vanishing points of the screen's x and y lines in 4+ views (seed 002).

In each view the decoded maps give, for every screen row and column, the image line on
which it appears; all images of screen lines y = const meet at the vanishing point of
the screen x direction, and likewise for x = const. Both are the first two columns of the
least-squares plane homography of the view (the common point of all those image lines).
The two vanishing directions are orthogonal in space: v_x^T w v_y = 0 with
w = K^-T K^-1. With zero skew and square pixels, w ~ [[1,0,-cx],[0,1,-cy],[-cx,-cy,c]],
one linear equation per view in (w11, w13, w23, w33); f^2 = c - cx^2 - cy^2.
"""

from __future__ import annotations

import numpy as np

from calibration.fit.ransac import DegenerateError


def vanishing_points(homography: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous image vanishing points of the screen x and y directions of one view."""
    h = np.asarray(homography, dtype=np.float64)
    return h[:, 0] / np.linalg.norm(h[:, 0]), h[:, 1] / np.linalg.norm(h[:, 1])


def vanishing_intrinsics(pairs: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """K (square pixels, zero skew) from >= 4 views' orthogonal vanishing-point pairs."""
    if len(pairs) < 4:
        raise DegenerateError(f"vanishing-point intrinsics need >= 4 views, got {len(pairs)}")
    rows = []
    for a, b in pairs:
        rows.append([a[0] * b[0] + a[1] * b[1], a[0] * b[2] + a[2] * b[0],
                     a[1] * b[2] + a[2] * b[1], a[2] * b[2]])
    rows_arr = np.array(rows)
    rows_arr /= np.linalg.norm(rows_arr, axis=1, keepdims=True)
    _, sv, vt = np.linalg.svd(rows_arr)
    if sv[-2] < 1e-9 * sv[0]:
        raise DegenerateError("vanishing points: views are degenerate (too similar orientations)")
    _, w13, w23, w33 = vt[-1] / vt[-1][0]
    cx, cy = -w13, -w23
    f2 = w33 - cx * cx - cy * cy
    if not f2 > 0:
        raise DegenerateError("vanishing points: no real focal length (fronto-parallel views?)")
    f = float(np.sqrt(f2))
    return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
