"""Pixel-space fits on rendered boards (hw_mocks.board) against the simulator's truth: the
bow, an outlier corner, the observations entry and the model that refuses sparse points."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibration.fit.sparse.calibrate import calibrate_observations
from calibration.fit.sparse.fit import ObservationFitError, fit_observations
from calibration.fit.sparse.options import ObservationOptions
from tests.calibration.targets.conftest import SIM_BOARD


def test_bow_is_recovered_within_two_sigma(simulated):
    cam, views, _ = simulated
    fit = fit_observations(views, "opencv5", ObservationOptions(target="fit"))
    tgt = fit.stats["target"]
    assert abs(tgt["bow_x_mm"] - SIM_BOARD.bow_x_mm) <= 2 * tgt["bow_x_std_mm"]
    assert abs(tgt["bow_y_mm"] - SIM_BOARD.bow_y_mm) <= 2 * tgt["bow_y_std_mm"]
    assert tgt["bow_x_std_mm"] < 0.05  # a real measurement, not a shrug
    # a flat fit of the bowed board is biased: its focal length misses the truth
    flat = fit_observations(views, "opencv5", ObservationOptions(target="flat"))
    fx_std = fit.stats["param_std"]["fx"]
    assert abs(fit.model.fx - cam.fx) <= 3 * fx_std
    assert abs(flat.model.fx - cam.fx) > abs(fit.model.fx - cam.fx)


def _with_moved_corner(views, view, row, shift_px):
    moved = [dataclasses.replace(v, image_xy=v.image_xy.copy()) for v in views]
    moved[view].image_xy[row, 0] += shift_px
    return moved


def test_a_moved_corner_is_an_outlier_and_changes_nothing(simulated):
    _, views, _ = simulated
    opts = ObservationOptions(target="fit")
    moved = _with_moved_corner(views, 3, 20, 5.0)
    fit = fit_observations(moved, "opencv5", opts)
    assert 20 in fit.stats["per_pose"][3]["outliers"]
    # the same fit with that corner not observed at all
    without = [dataclasses.replace(v) for v in views]
    without[3] = dataclasses.replace(views[3], weight=views[3].weights().copy())
    without[3].weight[20] = 0.0
    ref = fit_observations(without, "opencv5", opts)
    std = np.array([ref.stats["param_std"][n] for n in ref.model.param_names()])
    # the same optimum, to the solver's convergence (far below the uncertainty)
    assert np.all(np.abs(fit.model.get_params() - ref.model.get_params()) <= 1e-4 * std)
    # without rejection the moved corner drags the fit
    raw = fit_observations(moved, "opencv5", ObservationOptions(target="fit", outlier_rounds=0))
    assert raw.stats["rms_px"] > 1.5 * fit.stats["rms_px"]


def test_observation_entry_stats_and_refusals(simulated):
    _, views, _ = simulated
    result = calibrate_observations(views, "opencv5", options={"target": "fit"},
                                    cross_validate_folds=2)
    st = result.model.stats
    assert st["sigma_estimated"] and 0 < st["sigma_px"] < 0.2
    assert st["cross_validation"]["verdict"] in ("agree", "disagree")
    sig = np.array(st["projection_sigma_px"]["values"], dtype=float)  # NaN: no ray there
    assert sig.shape == (24, 32) and np.all(sig[6:18, 8:24] > 0)
    assert sig[12, 16] < 0.5 * np.nanmax(sig)  # best known where the board was seen
    assert len(result.residuals) == len(views)
    for model in ("opencv-rational", "fisheye"):  # every parametric model takes observations
        other = calibrate_observations(views, model, options={"target": "fit"})
        assert other.stats["rms_px"] < 1.2 * st["rms_px"]
    with pytest.raises(ValueError, match="raygrid cannot be fitted to target obs"):
        calibrate_observations(views, "raygrid")
    with pytest.raises(ValueError, match=r"options\.outlier_sigma"):
        calibrate_observations(views, "opencv5", options={"outlier_sigma": 0.5})
    with pytest.raises(ObservationFitError, match="needs >= 3 views"):
        fit_observations(views[:2], "opencv5")
    few = [dataclasses.replace(views[0], weight=np.zeros(views[0].count)), *views[1:]]
    with pytest.raises(ObservationFitError, match=r"view 0 \(sim0\) has 0 usable points"):
        fit_observations(few, "opencv5")
