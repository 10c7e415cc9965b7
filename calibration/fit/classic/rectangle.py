"""Intrinsics from the two vanishing points of a rectangle in 4+ views (Lu & Whangbo,
"A Practical Camera Calibration System on Mobile Phones").

The rectangle's sides give two vanishing points A, B per view whose directions are
orthogonal: A^T w B = 0 with w = K^-T K^-1 (the image of the absolute conic). With zero
skew, w ~ [[a, 0, d], [0, b, e], [d, e, c]], which is the paper's equation 4,
(cx - uA)(cx - uB)/fx^2 + (cy - vA)(cy - vB)/fy^2 + 1 = 0: one linear equation per view
in (a, b, d, e, c); with square pixels a = b. Solved in normalized image coordinates,
then reweighted by the propagated vanishing-point covariance (maximum-likelihood weights).
"""

from __future__ import annotations

import numpy as np

from calibration.fit.classic.estimate import IntrinsicsEstimate, monte_carlo_std, normalizer
from calibration.fit.classic.lines import Point, sample_points
from calibration.fit.ransac import DegenerateError

_REWEIGHT = 3
_MC_SAMPLES = 200


def vanishing_points(homography: np.ndarray) -> tuple[Point, Point]:
    """The vanishing points of a plane's x and y directions: the first two columns of its
    plane-to-image homography (for decoded maps: the common point of every decoded iso-y /
    iso-x line). No covariance is attached (zero), so no reweighting or Monte Carlo std."""
    h = np.asarray(homography, dtype=np.float64)
    z = np.zeros((3, 3))
    return (Point(h[:, 0] / np.linalg.norm(h[:, 0]), z),
            Point(h[:, 1] / np.linalg.norm(h[:, 1]), z))


def _rows(a: np.ndarray, b: np.ndarray, square: bool) -> np.ndarray:
    """Coefficient rows of A^T w B = 0 in (a, b, d, e, c), or (a, d, e, c) with a = b."""
    xx, yy = a[:, 0] * b[:, 0], a[:, 1] * b[:, 1]
    xz = a[:, 0] * b[:, 2] + a[:, 2] * b[:, 0]
    yz = a[:, 1] * b[:, 2] + a[:, 2] * b[:, 1]
    zz = a[:, 2] * b[:, 2]
    if square:
        return np.stack([xx + yy, xz, yz, zz], axis=1)
    return np.stack([xx, yy, xz, yz, zz], axis=1)


def _omega(x: np.ndarray, square: bool) -> np.ndarray:
    """w from the solution vector."""
    a, b, d, e, c = (x[0], x[0], x[1], x[2], x[3]) if square else x
    return np.array([[a, 0, d], [0, b, e], [d, e, c]])


def _solve(a: np.ndarray, b: np.ndarray, ca: np.ndarray | None, cb: np.ndarray | None,
           square: bool) -> np.ndarray:
    """Normalized K from normalized vanishing-point pairs (N, 3) with covariances (N, 3, 3)."""
    rows = _rows(a, b, square)
    rows = rows / np.linalg.norm(rows, axis=1, keepdims=True)
    pad = np.zeros((max(rows.shape[1] - rows.shape[0], 0), rows.shape[1]))  # exactly determined
    w = np.ones(len(rows))
    for it in range(_REWEIGHT + 1):
        _, sv, vt = np.linalg.svd(np.vstack([rows * np.sqrt(w)[:, None], pad]))
        if sv[-2] < 1e-10 * sv[0]:
            raise DegenerateError("vanishing points: the views are degenerate (too similar "
                                  "orientations, or a side parallel to the image in all views)")
        x = vt[-1]
        if ca is None or cb is None or it == _REWEIGHT:
            break
        om = _omega(x, square)
        oa, ob = a @ om, b @ om  # d(A^T w B)/dB = w A, d/dA = w B
        var = np.einsum("ni,nij,nj->n", ob, ca, ob) + np.einsum("ni,nij,nj->n", oa, cb, oa)
        norm = np.linalg.norm(_rows(a, b, square), axis=1)
        w = norm**2 / np.maximum(var, 1e-300)
        w /= w.mean()
    om = _omega(x, square)
    a_, b_, d_, e_, c_ = om[0, 0], om[1, 1], om[0, 2], om[1, 2], om[2, 2]
    if a_ * b_ <= 0:
        raise DegenerateError("vanishing points: no real solution (fx^2 and fy^2 differ in sign)")
    cx, cy = -d_ / a_, -e_ / b_
    lam = c_ - d_ * d_ / a_ - e_ * e_ / b_
    fx2, fy2 = lam / a_, lam / b_
    if not (fx2 > 0 and fy2 > 0):
        raise DegenerateError("vanishing points: no real focal length (noisy or near "
                              "fronto-parallel views)")
    return np.array([[np.sqrt(fx2), 0, cx], [0, np.sqrt(fy2), cy], [0, 0, 1.0]])


def rectangle_intrinsics(
    pairs: list[tuple[Point, Point]], image_size: tuple[int, int], *,
    square_pixels: bool = False, rng: np.random.Generator | None = None,
    mc_samples: int = _MC_SAMPLES,
) -> IntrinsicsEstimate:
    """K (zero skew; fx = fy when `square_pixels`) from per-view orthogonal vanishing points.

    Needs >= 4 views (>= 3 with square pixels). With covariances on the points the
    equations are reweighted and the parameters' std is estimated by Monte Carlo.
    """
    need = 3 if square_pixels else 4
    if len(pairs) < need:
        raise DegenerateError(f"rectangle intrinsics ({'square' if square_pixels else 'fx != fy'}"
                              f" pixels) need >= {need} views, got {len(pairs)}")
    t = normalizer(image_size)
    tinv = np.linalg.inv(t)

    def norm(pts: list[Point]) -> tuple[np.ndarray, np.ndarray]:
        p = np.array([t @ q.p for q in pts])
        c = np.array([t @ q.cov @ t.T for q in pts])
        return p, c

    a, ca = norm([p for p, _ in pairs])
    b, cb = norm([q for _, q in pairs])
    if not (np.any(ca) or np.any(cb)):  # no uncertainty given: equal weights, no Monte Carlo
        ca = cb = None
        mc_samples = 0
    k = tinv @ _solve(a, b, ca, cb, square_pixels)
    k /= k[2, 2]
    residual = _residual_deg(k, [p.p for p, _ in pairs], [q.p for _, q in pairs])
    rng = rng or np.random.default_rng(0)

    def redraw(g: np.random.Generator) -> np.ndarray:
        aa = np.array([t @ sample_points(p, 1, g)[0] for p, _ in pairs])
        bb = np.array([t @ sample_points(q, 1, g)[0] for _, q in pairs])
        kk = tinv @ _solve(aa, bb, ca, cb, square_pixels)
        return kk / kk[2, 2]

    std, failed = monte_carlo_std(redraw, mc_samples, rng) if mc_samples else ({}, 0)
    name = "rectangle-square" if square_pixels else "rectangle"
    return IntrinsicsEstimate(k, name, len(pairs), std,
                              {"angle_residual_deg_rms": residual, "mc_samples": mc_samples,
                               "mc_failed": failed})


def _residual_deg(k: np.ndarray, a: list[np.ndarray], b: list[np.ndarray]) -> float:
    """RMS deviation from 90 degrees of the angle between each view's two back-projected rays."""
    kinv = np.linalg.inv(k)
    da = np.array([kinv @ p for p in a])
    db = np.array([kinv @ p for p in b])
    cos = np.abs(np.sum(da * db, axis=1)) / np.linalg.norm(da, axis=1) / np.linalg.norm(db, axis=1)
    return float(np.sqrt(np.mean((90.0 - np.degrees(np.arccos(np.clip(cos, 0, 1)))) ** 2)))
