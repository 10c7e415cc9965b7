"""Image lines and their intersections, with first-order uncertainty.

Lines are homogeneous 3-vectors l (l . [u, v, 1] = 0) in pixel coordinates with a 3x3
covariance; points (vanishing points, corners) are homogeneous 3-vectors of unit norm with
a 3x3 covariance in that tangent space, so points at or near infinity stay finite.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.fit.ransac import DegenerateError


@dataclass(frozen=True)
class Line:
    """A fitted image line: homogeneous `l` (unit normal in l[:2]), covariance, fit statistics."""

    l: np.ndarray  # (3,)
    cov: np.ndarray  # (3, 3)
    rms_px: float  # RMS orthogonal residual of the points used
    n_points: int


@dataclass(frozen=True)
class Point:
    """A homogeneous image point of unit norm with its 3x3 covariance."""

    p: np.ndarray  # (3,)
    cov: np.ndarray  # (3, 3)

    def pixel(self) -> np.ndarray:
        """(u, v) pixel coordinates (inf for a point at infinity)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.p[:2] / self.p[2]


def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v]_x."""
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def fit_line(points: np.ndarray, weights: np.ndarray | None = None,
             sigma_px: float | None = None) -> Line:
    """Weighted total-least-squares line through (N, 2) points (N >= 3).

    Point noise is `sigma_px` (isotropic, per unit weight), or estimated from the
    residuals when None. The covariance follows from the angle and offset variances
    sigma^2 / sum(w t^2) and sigma^2 / sum(w) about the weighted centroid.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"fit_line: expected (N, 2) points, got {pts.shape}")
    n = len(pts)
    if n < 3:
        raise DegenerateError(f"line fit needs >= 3 points, got {n}")
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    c = (w[:, None] * pts).sum(axis=0) / w.sum()
    d = pts - c
    scatter = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(axis=0)
    evals, evecs = np.linalg.eigh(scatter)
    normal, along = evecs[:, 0], evecs[:, 1]
    if evals[1] <= 0:
        raise DegenerateError("line fit: points are all at one place")
    res = d @ normal
    rms = float(np.sqrt(np.sum(w * res**2) / w.sum()))
    s2 = sigma_px**2 if sigma_px is not None else float(np.sum(w * res**2) / max(n - 2, 1))
    var_theta = s2 / evals[1]  # evals[1] = sum w t^2
    var_off = s2 / w.sum()
    l = np.array([normal[0], normal[1], -normal @ c])
    j_theta = np.array([along[0], along[1], -along @ c])
    j_off = np.array([0.0, 0.0, -1.0])
    cov = var_theta * np.outer(j_theta, j_theta) + var_off * np.outer(j_off, j_off)
    return Line(l, cov, rms, n)


def intersect(a: Line, b: Line) -> Point:
    """The intersection of two lines (a x b, normalized) with its propagated covariance."""
    p = np.cross(a.l, b.l)
    cov = _skew(b.l) @ a.cov @ _skew(b.l).T + _skew(a.l) @ b.cov @ _skew(a.l).T
    return _unit_point(p, cov)


def _unit_point(p: np.ndarray, cov: np.ndarray) -> Point:
    """Normalize a homogeneous point to unit norm (and its covariance to the tangent space)."""
    norm = np.linalg.norm(p)
    if norm == 0:
        raise DegenerateError("intersection: the lines coincide")
    q = p / norm
    j = (np.eye(3) - np.outer(q, q)) / norm
    return Point(q, j @ cov @ j.T)


def common_point(lines: list[Line], iterations: int = 3) -> Point:
    """Maximum-likelihood common point of >= 2 lines (a vanishing point of a line family).

    Minimizes sum (l_i . p)^2 / (p^T C_i p) over unit p by reweighted eigen-solutions;
    the covariance is the pseudo-inverse of the weighted moment matrix (tangent space).
    """
    if len(lines) < 2:
        raise DegenerateError(f"a common point needs >= 2 lines, got {len(lines)}")
    if len(lines) == 2:
        return intersect(lines[0], lines[1])
    ls = np.array([ln.l for ln in lines])
    cs = np.array([ln.cov for ln in lines])
    w = np.ones(len(lines))
    p = np.zeros(3)
    for _ in range(iterations):
        m = (w[:, None, None] * ls[:, :, None] * ls[:, None, :]).sum(axis=0)
        _, vecs = np.linalg.eigh(m)
        p = vecs[:, 0]
        w = 1.0 / np.maximum(np.einsum("i,nij,j->n", p, cs, p), 1e-300)
    m = (w[:, None, None] * ls[:, :, None] * ls[:, None, :]).sum(axis=0)
    proj = np.eye(3) - np.outer(p, p)
    cov = np.linalg.pinv(proj @ m @ proj, rcond=1e-12)
    return Point(p, proj @ cov @ proj)


def grid_vanishing_points(pixels: np.ndarray, sigma_px: float | None = None) -> tuple[Point, Point]:
    """Vanishing points of the rows (x direction) and columns (y direction) of an
    (ny, nx, 2) grid of corner pixels, each from a line fitted to every row/column."""
    rows = [fit_line(pixels[j], sigma_px=sigma_px) for j in range(pixels.shape[0])]
    cols = [fit_line(pixels[:, i], sigma_px=sigma_px) for i in range(pixels.shape[1])]
    return common_point(rows), common_point(cols)


def sample_points(pt: Point, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) perturbed unit points drawn from the first-order distribution (Monte Carlo)."""
    evals, evecs = np.linalg.eigh(pt.cov)
    z = rng.standard_normal((n, 3)) * np.sqrt(np.maximum(evals, 0))
    q = pt.p + z @ evecs.T
    return q / np.linalg.norm(q, axis=1, keepdims=True)
