"""Classic estimators through OpenCV: non-planar PnP (3 solvers), USAC PnP/homography,
adaptive DLT RANSAC."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.fit.classic.dlt import decompose_projection, ransac_dlt
from calibration.fit.classic.robust import PNP_METHODS, pnp_ransac, solve_pnp, usac_homography
from calibration.fit.ransac import DegenerateError, required_iterations

K = np.array([[520.0, 0, 331.0], [0, 530.0, 233.5], [0, 0, 1]])
R = cv2.Rodrigues(np.array([0.2, -0.3, 0.1]))[0]
T = np.array([10.0, -20.0, 600.0])


def _scene(rng: np.random.Generator, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    x = rng.uniform(-150, 150, (n, 3))
    p = (x @ R.T + T) @ K.T
    return x, p[:, :2] / p[:, 2:]


def _outliers(u: np.ndarray, frac: float, rng: np.random.Generator) -> np.ndarray:
    out = rng.random(len(u)) < frac
    u[out] = rng.uniform(0, 640, (int(out.sum()), 2))
    return out


@pytest.mark.parametrize("method", sorted(PNP_METHODS))
def test_nonplanar_pnp_exact(method: str) -> None:
    x, u = _scene(np.random.default_rng(0))
    r, t, rms = solve_pnp(x, u, K, method=method)
    np.testing.assert_allclose(r, R, atol=1e-9)
    np.testing.assert_allclose(t, T, atol=1e-6)
    assert rms < 1e-6
    with pytest.raises(ValueError, match="method"):
        solve_pnp(x, u, K, method="p3p-typo")


def test_usac_pnp_and_adaptive_dlt_at_60_percent_outliers() -> None:
    rng = np.random.default_rng(1)
    x, u = _scene(rng)
    u += 0.1 * rng.standard_normal(u.shape)
    out = _outliers(u, 0.6, rng)
    r, t, inl = pnp_ransac(x, u, K, threshold_px=1.0)
    assert inl[~out].mean() > 0.97 and inl[out].mean() < 0.02
    assert np.degrees(np.arccos((np.trace(r.T @ R) - 1) / 2)) < 0.05
    assert np.linalg.norm(t - T) < 0.5
    stats: dict[str, float] = {}
    p, inl = ransac_dlt(x, u, 1.0, rng, stats=stats)
    assert inl[~out].mean() > 0.97 and inl[out].mean() < 0.02
    # adaptive: stops near the theoretical count for the true inlier ratio, not at the cap
    assert required_iterations(0.4, 6, 0.999) < stats["samples"] < 4 * required_iterations(
        0.4, 6, 0.999)
    clean: dict[str, float] = {}
    ransac_dlt(x[~out], u[~out], 1.0, rng, stats=clean)
    assert clean["samples"] < 20
    np.testing.assert_allclose(decompose_projection(p)[0], K, rtol=0.01, atol=3.0)


def test_usac_homography_and_iteration_count() -> None:
    rng = np.random.default_rng(2)
    h = np.array([[1.1, 0.05, 20], [0.02, 0.95, -10], [1e-4, -5e-5, 1]])
    s = rng.uniform(0, 500, (400, 2))
    q = np.c_[s, np.ones(400)] @ h.T
    d = q[:, :2] / q[:, 2:] + 0.1 * rng.standard_normal((400, 2))
    out = _outliers(d, 0.6, rng)
    est, inl = usac_homography(s, d, 1.0)
    assert inl[~out].mean() > 0.97 and inl[out].mean() < 0.02
    grid = np.c_[np.linspace(0, 500, 5), np.linspace(0, 500, 5)[::-1], np.ones(5)]
    a, b = grid @ h.T, grid @ est.T
    assert np.max(np.linalg.norm(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:], axis=1)) < 0.2
    assert required_iterations(1.0, 4, 0.99) == 1.0
    assert 70 < required_iterations(0.5, 4, 0.99) < 75  # log(0.01) / log(1 - 1/16) = 71.4
    with pytest.raises(DegenerateError, match=">= 4"):
        usac_homography(s[:3], d[:3], 1.0)


def test_public_interface() -> None:
    import calibration.fit as fit

    for name in fit.__all__:
        assert getattr(fit, name) is not None
    with pytest.raises(fit.DegenerateError, match="collinear"):
        fit.fit_homography(np.c_[np.arange(6.0), np.arange(6.0)], np.zeros((6, 2)))
    assert issubclass(fit.NotPositiveDefiniteError, fit.DegenerateError)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        _ = fit.nope
