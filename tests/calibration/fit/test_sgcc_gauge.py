"""The sparse gauge null-space basis of the sGCC fit equals the dense products it replaces."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.fit.sgcc.gauge import GaugeBasis
from calibration.fit.sgcc.lm import gauge_constraints
from calibration.models.bspline import SplineGrid


@pytest.mark.parametrize("n_comp", [2, 4])
def test_gauge_basis_is_an_orthonormal_null_space_and_its_products_are_dense_ones(n_comp):
    grid = SplineGrid((160, 120), (5, 4))
    n = grid.size * n_comp + 12  # two poses
    cons = gauge_constraints(grid, n_comp, n)
    gauge = GaugeBasis.null_space_of(cons)
    z = np.stack([gauge.expand(e) for e in np.eye(gauge.size)], axis=1)  # dense Z
    assert z.shape == (n, n - len(cons))
    assert np.allclose(cons @ z, 0, atol=1e-12)
    assert np.allclose(z.T @ z, np.eye(gauge.size), atol=1e-12)
    rng = np.random.default_rng(n_comp)
    a = rng.normal(size=(n, n))
    h = a @ a.T
    g = rng.normal(size=n)
    assert np.allclose(gauge.reduce(h), z.T @ h @ z, rtol=1e-12, atol=1e-10)
    assert np.allclose(gauge.reduce_vector(g), z.T @ g, atol=1e-12)
    c = gauge.reduce(h)
    assert np.allclose(gauge.expand_matrix(c), z @ c @ z.T, rtol=1e-12, atol=1e-10)


def test_selection_frees_only_the_given_columns():
    gauge = GaugeBasis.selection(10, np.arange(4, 10))
    h = np.arange(100.0).reshape(10, 10)
    assert np.array_equal(gauge.reduce(h), h[4:, 4:])
    assert np.array_equal(gauge.expand(np.ones(6)), np.r_[np.zeros(4), np.ones(6)])
