"""The sGCC exponential map's rows and Jacobian (the fit's per-pixel kernel) against a direct
evaluation and central differences, across the series branch at small angles."""

from __future__ import annotations

import numpy as np

from calibration.models.sgcc import expmap, expmap_jacobian_rows, expmap_rows


def _coordinates() -> tuple[np.ndarray, np.ndarray]:
    """Exp-map coordinates from 0 through the small-angle series (rho < 1e-3) to 170 degrees."""
    rng = np.random.default_rng(7)
    rho = np.r_[0.0, 1e-9, 1e-5, 9.99e-4, 1e-3, 1.001e-3, rng.uniform(0, 2.97, 500)]
    phi = rng.uniform(0, 2 * np.pi, rho.size)
    return rho * np.cos(phi), rho * np.sin(phi)


def test_jacobian_rows_are_the_unit_directions_and_their_derivatives() -> None:
    a, b = _coordinates()
    r, jac = expmap_jacobian_rows(a, b)
    assert np.allclose(r, expmap_rows(a, b), rtol=0, atol=1e-15)
    assert np.allclose(r.T, expmap(np.c_[a, b]), rtol=0, atol=1e-15)
    assert np.allclose(np.linalg.norm(r, axis=0), 1.0, rtol=0, atol=1e-15)
    h = 1e-6
    for k, (da, db) in enumerate(((h, 0.0), (0.0, h))):
        num = (expmap_rows(a + da, b + db) - expmap_rows(a - da, b - db)) / (2 * h)
        assert np.allclose(jac[:, k], num, rtol=0, atol=1e-9)
