"""The sGCC device path (`sgcc.device.DeviceProblem`, run here with NumPy as the array module)
against the threaded CPU path: same residuals, normal equations and fitted spline."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from calibration.fit.observations import observations
from calibration.fit.sgcc import calibrate as generic
from calibration.fit.sgcc import lm as sgcc_lm
from calibration.fit.sgcc.calibrate import calibrate_generic
from calibration.fit.sgcc.device import DeviceProblem
from calibration.fit.sgcc.initial import initial_state
from calibration.fit.sgcc.problem import Problem
from calibration.fit.sgcc.robust import block_weights
from calibration.models.bspline import SplineGrid
from calibration.shared.plan import ScreenGeometry
from hw_mocks import cameras, poses, synthetic

W, H = 160, 120
SCREEN = ScreenGeometry(1920, 1080, (0.2745, 0.2745))


@pytest.fixture(scope="module")
def maps():
    """Decoded maps of 3 random poses of a non-central camera."""
    cam = cameras.smooth_noncentral(W, H)
    rng = np.random.default_rng(7)
    ps = poses.random_poses(cam, SCREEN, 3, rng, distance_mm=(150.0, 450.0), min_coverage=0.2)
    return [synthetic.synthetic_maps(cam, p, SCREEN, rng=rng)[0] for p in ps]


def _close(got, want, rtol=1e-10):
    """Equal to rtol, relative to each entry and to the largest entry (near-zero entries)."""
    np.testing.assert_allclose(got, want, rtol=rtol, atol=rtol * np.abs(want).max())


@pytest.mark.parametrize("n_comp", [2, 4])
def test_device_problem_equals_threaded_problem(maps, n_comp):
    obs = observations(maps, SCREEN)
    grid = SplineGrid((W, H), (8, 8))
    st = initial_state(obs, grid, n_comp)
    rng = np.random.default_rng(n_comp)
    if n_comp == 4:
        st.coeffs[:, 2:] = rng.normal(size=(grid.size, 2)) * 0.5  # non-zero origins, mm
    st.coeffs[: 4 * grid.n_ctrl[0], 0] += 3.0  # top rows look backwards: ok is False there
    prob = Problem(grid, n_comp, obs)
    res, ok = prob.residuals(st)
    assert 0.2 < ok.mean() < 0.95
    wt = rng.uniform(0.1, 2.0, ok.size) * (rng.uniform(size=ok.size) > 0.2) * ok
    # Default spans (one per pose) and small ones that cut cell segments and poses.
    for chunk in (1 << 19, 777):
        dev = DeviceProblem(prob, np, chunk)
        res_d, ok_d = dev.residuals(st)
        np.testing.assert_array_equal(ok_d, ok)
        _close(res_d, res)
        for spline in (True, False):
            h, grad = prob.normal_equations(st, wt, spline)
            h_d, grad_d = dev.normal_equations(st, wt, spline)
            _close(h_d, h)
            _close(grad_d, grad)
            # LM's fused pass: residuals, then normal equations with their own robust weights
            for hessian in (True, False):
                fused = prob.residuals_and_normal_equations(st, block_weights(3.0, 8.0), spline,
                                                            hessian)
                fused_d = dev.residuals_and_normal_equations(st, block_weights(3.0, 8.0), spline,
                                                             hessian)
                np.testing.assert_array_equal(fused_d[1], fused[1])
                for k in (0, 2, 3) if hessian else (0, 3):
                    _close(fused_d[k], fused[k])


def test_cupy_option_runs_the_device_path(maps, monkeypatch):
    """options={"xp": "cupy"} with NumPy standing in for CuPy: the device problem fits the
    same spline as the default threaded path."""
    opts = {"cells": [8, 8]}
    ref = calibrate_generic(maps, SCREEN, "sgcc-noncentral", options=opts)
    asked = []

    def fake_module(name):
        asked.append(name)
        return np

    monkeypatch.setattr(generic, "array_module", fake_module)
    monkeypatch.setattr(sgcc_lm, "array_module", fake_module)
    made = []
    monkeypatch.setattr(DeviceProblem, "residuals", _spy(DeviceProblem.residuals, made))
    got = calibrate_generic(maps, SCREEN, "sgcc-noncentral", options={**opts, "xp": "cupy"})
    assert made and set(asked) == {"cupy"}
    assert got.stats["iterations"] == ref.stats["iterations"]
    # Rounding-level differences in the normal equations reach the result through the weak
    # (uncovered-cell) directions: re-chunking the threaded path alone moves the spline by
    # 1.5e-6 sigma and its sigmas by 2e-5 relative.
    sd = np.sqrt(np.diag(ref.model.covariance))
    assert np.max(np.abs(got.model.get_params() - ref.model.get_params()) / sd) < 1e-5
    np.testing.assert_allclose(np.sqrt(np.diag(got.model.covariance)), sd, rtol=1e-4)


def _spy(method, calls):
    """`method` that also records each call in `calls`."""

    def wrapped(self, *args, **kwargs):
        calls.append(method.__name__)
        return method(self, *args, **kwargs)

    return wrapped


def test_unknown_xp_is_a_clear_error(maps):
    for bad in ("torch", 3):
        with pytest.raises(ValueError, match=r"options\.xp: Input should be 'numpy' or 'cupy'"):
            calibrate_generic(maps, SCREEN, "sgcc", options={"xp": bad})


@pytest.mark.skipif(importlib.util.find_spec("cupy") is not None, reason="CuPy is installed")
def test_missing_cupy_is_a_clear_error(maps):
    with pytest.raises(ValueError, match=r"options\.xp: 'cupy' requested but not importable"):
        calibrate_generic(maps, SCREEN, "sgcc", options={"xp": "cupy"})
