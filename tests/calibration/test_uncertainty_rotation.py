"""A fit's ray uncertainty without its rotation-like part, the one two fits are compared
against after their best rotation: a Jacobian column that only rotates every ray goes, one
that bends rays stays, and the remaining variance summed over the image never exceeds the
whole (the projection is orthogonal over all pixels together, not pixel by pixel). An sGCC
model's, from its sparse Jacobian in chunks of pixels, is the dense computation's."""

from __future__ import annotations

import numpy as np

from calibration.models.sgcc import SGCCModel, SGCCNonCentralModel
from calibration.uncertainty import (
    direction_jacobian,
    ray_sigma,
    sensor_grid,
    spline_ray_sigma_without_rotation,
    without_rotation,
)


def directions(n: int = 200) -> np.ndarray:
    """Unit rays of a 90-degree field of view, as a pinhole camera sees them."""
    px = sensor_grid((640, 480), 20, 10)[:n]
    d = np.column_stack([(px[:, 0] - 320) / 320, (px[:, 1] - 240) / 320, np.ones(len(px))])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_a_pure_rotation_is_taken_out_and_a_bend_is_kept():
    d = directions()
    omega = np.array([1e-3, -2e-3, 5e-4])
    rotate = np.cross(omega, d)  # every ray turned by omega
    radial = d - d[:, 2:3] * np.array([0.0, 0.0, 1.0])  # rays pushed outwards: a lens term
    bend = radial - d * np.einsum("na,na->n", radial, d)[:, None]  # kept perpendicular to d
    jd = np.stack([rotate, bend * 1e-3], axis=2)  # (N, 3, 2)
    out = without_rotation(jd, d)
    assert np.abs(out[:, :, 0]).max() < 1e-12 * np.abs(rotate).max() + 1e-18
    assert np.linalg.norm(out[:, :, 1]) > 0.5 * np.linalg.norm(jd[:, :, 1])


def test_the_rotation_free_variance_over_the_image_is_below_the_whole():
    rng = np.random.default_rng(3)
    d = directions()
    jd = rng.normal(size=(len(d), 3, 6)) * 1e-3
    jd -= d[:, :, None] * np.einsum("nap,na->np", jd, d)[:, None, :]  # directions stay unit
    root = rng.normal(size=(6, 6))
    cov = root @ root.T
    whole, free = ray_sigma(jd, cov), ray_sigma(without_rotation(jd, d), cov)
    assert np.sum(free**2) < np.sum(whole**2)
    d[5] = np.nan  # a pixel without a ray does not spoil the others
    assert np.isfinite(without_rotation(jd, d)[np.arange(len(d)) != 5]).all()


def test_an_sgcc_models_sparse_rotation_free_sigma_is_the_dense_ones():
    rng = np.random.default_rng(5)
    for cls in (SGCCModel, SGCCNonCentralModel):
        model = cls((80, 60), cells=(4, 3))
        model.set_params(0.3 * rng.normal(size=model.get_params().size))
        root = rng.normal(size=(model.get_params().size,) * 2) * 1e-3
        model.covariance = root @ root.T
        px = sensor_grid((80, 60), 12, 9)
        dense = direction_jacobian(model, px, np.arange(model.get_params().size))
        want = ray_sigma(without_rotation(dense, model.unproject(px)[1]), model.covariance)
        got = spline_ray_sigma_without_rotation(model, px, chunk=7)  # chunks cut the pixels
        assert np.allclose(got, want, rtol=1e-6)
        assert np.sum(got**2) < np.sum(model.ray_std(px)[0] ** 2)
