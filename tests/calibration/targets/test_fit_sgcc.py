"""The sGCC models fitted to sparse target observations: at least as good as opencv5 on
OpenCV's real left images with an honest cross-validation, rays within their predicted
uncertainty of the simulated camera's truth, outliers, refusals."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibration.fit.sparse.calibrate import calibrate_observations
from calibration.fit.sparse.crossval import AGREE_RATIO
from calibration.fit.sparse.fit import ObservationFitError
from calibration.fit.sparse.options import ObservationOptions
from calibration.fit.sparse.sgcc import fit_sgcc_observations
from calibration.fit.sparse.uncertainty import projection_covariance

BOWED = ObservationOptions(target="fit")


def test_sgcc_fits_real_images_as_well_as_opencv5_and_cross_validates(sample_views):
    views = sample_views["left"]
    generic = calibrate_observations(views, "sgcc", options=BOWED, cross_validate_folds=2)
    parametric = calibrate_observations(views, "opencv5", options=BOWED)
    st = generic.stats
    assert st["rms_px"] <= parametric.stats["rms_px"]
    assert st["mesh"]["candidates"][-1]["points_per_cell"] >= st["mesh"]["min_points_per_cell"]
    cv = st["cross_validation"]
    # honest: the halves differ by about what their covariances predict, neither far more
    # (overconfident) nor far less (inflated)
    assert cv["verdict"] == "agree" and 0.5 <= cv["ratio"] <= AGREE_RATIO
    assert generic.model.stats["projection_sigma_px"]["median"] > 0
    assert np.isfinite(generic.model.covariance).all()


def _truth_error(cam, fit, views):
    """Normalized (z) and pixel errors of the fitted rays against the truth camera's at the
    observed pixels, after the rotation that best aligns the two camera frames."""
    pix = np.concatenate([v.image_xy for v in views])
    _, truth = cam.rays(pix[:, 0], pix[:, 1])
    _, model = fit.model.unproject(pix)
    u, _, vt = np.linalg.svd(model.T @ truth)
    rot = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt  # truth frame -> model frame
    rays = 1000.0 * truth @ rot.T
    diff = fit.model.project(rays) - pix
    cov = projection_covariance(fit.model, fit.intrinsics_covariance, rays)
    z2 = np.einsum("ni,nij,nj->n", diff, np.linalg.inv(cov), diff)
    return float(np.sqrt(np.mean(z2) / 2)), float(np.sqrt(np.mean(np.sum(diff**2, axis=1))))


def test_sgcc_rays_match_the_simulated_truth_within_their_uncertainty(simulated):
    cam, views, _ = simulated
    fit = fit_sgcc_observations(views, "sgcc", BOWED)
    ratio, rms = _truth_error(cam, fit, views)
    assert ratio <= AGREE_RATIO and rms < 0.3
    noncentral = fit_sgcc_observations(views, "sgcc-noncentral", BOWED)
    assert noncentral.stats["converged"] and noncentral.stats["rms_px"] < 0.3
    assert np.isfinite(noncentral.model.covariance).all()


def test_a_moved_corner_is_rejected(simulated):
    _, views, _ = simulated
    moved = [dataclasses.replace(v, image_xy=v.image_xy.copy()) for v in views]
    moved[3].image_xy[20, 0] += 5.0
    fit = fit_sgcc_observations(moved, "sgcc", BOWED)
    ref = fit_sgcc_observations(views, "sgcc", BOWED)
    for j, (row, before) in enumerate(zip(fit.stats["per_pose"], ref.stats["per_pose"],
                                          strict=True)):
        # the moved corner joins the outliers; nothing else changes
        assert row["outliers"] == sorted(before["outliers"] + ([20] if j == 3 else []))
    at = fit.stats["per_pose"][3]["outliers"].index(20)
    assert fit.stats["per_pose"][3]["outlier_residuals_px"][at] > 4.0
    assert fit.stats["rms_px"] == pytest.approx(ref.stats["rms_px"], rel=1e-3)


def test_too_few_points_are_refused_with_the_count(simulated):
    _, views, _ = simulated
    sparse = []
    for v in views[:4]:
        keep = np.zeros(v.count)
        keep[::6] = 1.0
        sparse.append(dataclasses.replace(v, weight=keep))
    with pytest.raises(ObservationFitError, match=r"\d+ points in 4 views are too few for an "
                       r"sGCC mesh.*needs >= 20 points per cell.*add about \d+ views like these"):
        fit_sgcc_observations(sparse, "sgcc")
