"""sGCC fit statistics: camera-px residuals through the local Jacobian dQ/d(u, v), shared
per-pixel ray evaluation across poses, against finite differences of the model's rays."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.fit.observations import PoseObs
from calibration.fit.sgcc import statistics
from calibration.fit.sgcc.statistics import fit_statistics
from calibration.models.sgcc import SGCCModel, SGCCNonCentralModel

W, H = 150, 100


def _screen_point(model, rc, tc, pix):
    """Screen-plane point (n, 2) mm where the model's rays of pixels (n, 2) meet z = 0."""
    o, d = model.unproject(pix)
    o_s, r_s = o @ rc.T + tc, d @ rc.T
    return o_s[:, :2] - (o_s[:, 2] / r_s[:, 2])[:, None] * r_s[:, :2]


def _reference(model, rc, tc, pix, res, sig):
    """px = -J^-1 res and |J^-1 diag(sigma)|^2 with J = dQ/d(u, v) by central differences."""
    h = 1e-3
    q = [_screen_point(model, rc, tc, pix + d) - _screen_point(model, rc, tc, pix - d)
         for d in (np.array([h, 0.0]), np.array([0.0, h]))]
    cols = [dq / (2 * h) for dq in q]
    jac = np.stack(cols, axis=2)  # (n, 2, 2): rows Q, columns u, v
    inv = np.linalg.inv(jac)
    px = -np.einsum("nij,nj->ni", inv, res)
    return px, np.sum((inv * sig[:, None, :]) ** 2, axis=(1, 2))


@pytest.mark.parametrize("cls", [SGCCModel, SGCCNonCentralModel])
@pytest.mark.parametrize("shift", [0.0, 0.5])  # integer pixels (shared blocks) or not (per pose)
def test_statistics_equal_finite_difference_jacobian(cls, shift, monkeypatch):
    monkeypatch.setattr(statistics, "_BLOCK", 997)  # many blocks, poses' pixels across them
    rng = np.random.default_rng(3)
    model = cls((W, H), (5, 4))
    uu, vv = (g.ravel() for g in np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float)))
    ab = np.c_[(uu - W / 2) * 0.006, (vv - H / 2) * 0.006] * (1 + 1e-5 * (uu - W / 2) ** 2)[:, None]
    model.coeffs[:, :2] = model.grid.fit(uu, vv, ab)  # a wide-angle lens with distortion
    if cls.n_components == 4:
        model.coeffs[:, 2:] = rng.normal(size=(model.grid.size, 2)) * 0.5
    obs, rcs, tcs, res, inl = [], [], [], [], []
    for _ in range(3):  # each pose sees its own random part of the image
        vv, uu = np.nonzero(rng.random((H, W)) < rng.uniform(0.3, 0.9))
        pix = np.c_[uu, vv].astype(np.float64) + shift
        sig = rng.uniform(0.01, 0.05, (len(pix), 2))
        obs.append(PoseObs(pix, rng.normal(size=(len(pix), 2)), sig))
        rcs.append(Rotation.from_rotvec(rng.normal(size=3) * 0.2).as_matrix())
        tcs.append(np.r_[rng.normal(size=2) * 5, -200.0])
        res.append(rng.normal(size=(len(pix), 2)) * 0.02)
        inl.append(rng.random(len(pix)) < 0.95)
    pitch = np.array([0.27, 0.28])
    out = fit_statistics(model, rcs, tcs, obs, res, inl, pitch, 0.9)
    for j, (px, row) in enumerate(out):
        keep = inl[j]
        ref_px, ref_e2 = _reference(model, rcs[j], tcs[j], obs[j].pixels[keep], res[j][keep],
                                    obs[j].sigma_mm[keep])
        assert np.allclose(px, ref_px, rtol=1e-5, atol=1e-9)
        assert row["n_points"] == keep.sum() and row["n_outliers"] == (~keep).sum()
        assert np.isclose(row["rms_px"], np.sqrt(np.mean(np.sum(ref_px**2, axis=1))), rtol=1e-5)
        assert np.isclose(row["expected_rms_px"], np.sqrt(np.mean(ref_e2) * 0.9), rtol=1e-5)
        screen = res[j][keep] / pitch
        assert np.isclose(row["rms_screen_px"], np.sqrt(np.mean(np.sum(screen**2, axis=1))))
