"""The closed-form pixel residual of an sGCC model (calibration/fit/sparse/ray_residual.py):
the model's own projection minus the observed pixel to first order, with exact derivatives
over the control values and the point, for the central and the non-central model."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.fit.sparse.ray_residual import ray_residual
from calibration.models.sgcc import SGCCModel, SGCCNonCentralModel, logmap


def _model(cls):
    """A 70-degree pinhole-like ray field with barrel distortion (and, if non-central, a
    smooth origin field of about a millimetre)."""
    model = cls((320, 240), (5, 4))
    u, v = np.meshgrid(np.linspace(-0.5, 319.5, 40), np.linspace(-0.5, 239.5, 30))
    x, y = (u.ravel() - 160) / 230, (v.ravel() - 120) / 230
    k = 1 - 0.15 * (x * x + y * y)
    d = np.stack([x * k, y * k, np.ones_like(x)], axis=1)
    values = [logmap(d)]
    if model.n_components == 4:
        values.append(np.stack([0.8 * x * x, -0.5 * x * y], axis=1))
    model.coeffs = model.grid.fit(u.ravel(), v.ravel(), np.concatenate(values, axis=1))
    return model


@pytest.mark.parametrize("cls", [SGCCModel, SGCCNonCentralModel])
def test_residual_is_the_projection_miss_with_exact_derivatives(cls):
    model = _model(cls)
    rng = np.random.default_rng(5)
    q = rng.uniform([40, 30], [280, 210], size=(25, 2))
    origin, direction = model.unproject(q)
    points = origin + 600.0 * direction
    shift = rng.normal(scale=0.3, size=q.shape)
    rr = ray_residual(model, q + shift, points)
    # the point projects to q, so it misses q + shift by -shift, to second order
    assert np.abs(rr.pixels + shift).max() < 0.02
    assert np.abs(model.project(points) - q).max() < 1e-6
    base = model.get_params()
    scale = np.abs(rr.d_coeffs).max()
    touched = np.flatnonzero(np.abs(rr.d_coeffs).max(axis=(0, 1)) > 0)
    for i in rng.choice(touched, 12, replace=False):
        step = 1e-7
        plus, minus = base.copy(), base.copy()
        plus[i] += step
        minus[i] -= step
        model.set_params(plus)
        rp = ray_residual(model, q + shift, points).pixels
        model.set_params(minus)
        rm = ray_residual(model, q + shift, points).pixels
        model.set_params(base)
        num = (rp - rm) / (2 * step)
        assert np.allclose(rr.d_coeffs[:, :, i], num, rtol=1e-5, atol=1e-6 * scale)
    for axis in range(3):
        dp = np.zeros(3)
        dp[axis] = 1e-4
        num = (ray_residual(model, q + shift, points + dp).pixels
               - ray_residual(model, q + shift, points - dp).pixels) / 2e-4
        assert np.allclose(rr.d_point[:, :, axis], num, rtol=1e-5,
                           atol=1e-6 * np.abs(rr.d_point).max())
