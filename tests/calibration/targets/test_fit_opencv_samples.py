"""Pixel-space fits on OpenCV's real sample chessboard images (both cameras, every image the
detector accepts): the same optimum as cv2.calibrateCamera on the same corners, and fits of
disjoint view halves that agree within their predicted difference."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.fit.sparse.crossval import cross_validate
from calibration.fit.sparse.fit import fit_observations
from calibration.fit.sparse.options import ObservationOptions


@pytest.mark.parametrize("side", ["left", "right"])
def test_opencv5_matches_calibrate_camera(sample_views, side):
    views = sample_views[side]
    fit = fit_observations(views, "opencv5", ObservationOptions(weights="equal"))
    inl = [np.ones(v.count, bool) for v in views]
    for row, mask in zip(fit.stats["per_pose"], inl, strict=True):
        mask[row["outliers"]] = False  # OpenCV gets the same corners the fit kept
    obj = [v.target_xyz[m].astype(np.float32) for v, m in zip(views, inl, strict=True)]
    img = [v.image_xy[m].astype(np.float32) for v, m in zip(views, inl, strict=True)]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 500, 1e-16)
    rms, k, dist, *_ = cv2.calibrateCamera(obj, img, views[0].image_size, None, None,
                                           criteria=crit)
    assert fit.stats["rms_px"] == pytest.approx(rms, rel=1e-6)
    ref = np.r_[k[0, 0], k[1, 1], k[0, 2], k[1, 2], dist.ravel()[:5]]
    std = np.array([fit.stats["param_std"][n] for n in fit.model.param_names()])
    assert np.all(np.abs(fit.model.get_params() - ref) <= 0.05 * std)


@pytest.mark.parametrize("side", ["left", "right"])
def test_cross_validation_halves_agree(sample_views, side):
    # the sample board is measurably bowed (~0.16 mm over its 125 mm height on the left
    # camera): its shape is fitted with the camera
    cv = cross_validate(sample_views[side], "opencv5", ObservationOptions(target="fit"))
    assert cv["verdict"] == "agree"
    pair = cv["pairs"][0]
    assert pair["rms_difference_px"] <= 2 * pair["rms_predicted_px"]
    assert [len(f) for f in cv["folds"]] == [7, 6]
