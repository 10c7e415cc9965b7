"""Undistortion maps, undistorted points and best-fitting OpenCV model of a fitted sGCC model."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.fit.sgcc.calibrate import calibrate_generic
from calibration.shared.plan import ScreenGeometry
from calibration.undistort import best_opencv_model, rectify_maps, undistort_points
from hw_mocks import cameras, poses, synthetic

W, H = 160, 120
SCREEN = ScreenGeometry(1920, 1080, (0.2745, 0.2745))


@pytest.fixture(scope="module")
def fitted():
    """An sgcc fit of a mild pinhole with 5-coefficient distortion."""
    cam = cameras.mild_pinhole(W, H)
    rng = np.random.default_rng(8)
    ps = poses.random_poses(cam, SCREEN, 3, rng)
    maps = [synthetic.synthetic_maps(cam, p, SCREEN, rng=rng)[0] for p in ps]
    return cam, calibrate_generic(maps, SCREEN, "sgcc", options={"cells": [6, 6]}).model


def test_remap_maps_and_undistorted_points_agree(fitted):
    _, model = fitted
    k = np.array([[130.0, 0, W / 2], [0, 130.0, H / 2], [0, 0, 1]])
    map_x, map_y = rectify_maps(model, k, (W, H))
    assert map_x.dtype == np.float32 and map_x.shape == (H, W)
    pix = np.array([[40.0, 30.0], [80.0, 60.0], [120.0, 90.0]])
    virt = undistort_points(model, pix, k)
    iu, iv = np.round(virt).astype(int).T
    back = np.stack([map_x[iv, iu], map_y[iv, iu]], axis=1)
    # The map at the nearest virtual pixel lands within ~1 px of the original pixel.
    assert np.all(np.abs(back - pix) < 1.0)


def test_best_opencv_model_of_a_pinhole_leaves_tiny_residual(fitted):
    _, model = fitted
    best = best_opencv_model(model, "opencv5")
    assert best["rms_px"] < 0.2  # includes extrapolated corners of the spline
    assert best["residual_px"].shape == (len(best["pixels"]),)
    with pytest.raises(ValueError, match="kind"):
        best_opencv_model(model, "nonsense")
