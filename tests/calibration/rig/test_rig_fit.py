"""The joint rig fit against simulated ground truth: extrinsics within their stated
uncertainty, cameras tied through a chain of views, disconnected cameras refused."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.fit.rig.calibrate import calibrate_rig, heldout_block
from calibration.fit.rig.heldout import score_view
from calibration.fit.rig.inputs import RigInput
from calibration.fit.rig.transforms import to_rvec
from hw_mocks.cameras import mild_pinhole
from hw_mocks.rig_truth import (
    RigTruth,
    camera_at,
    grid_points,
    shared_views,
    view_observations,
)
from tests.calibration.rig.conftest import SCREEN


def _normalized_errors(rig, truth, first: str, second: str) -> np.ndarray:
    """(rotation vector, translation) error of `second` in `first`'s frame over its sigma."""
    rot, t = rig.relative(first, second)
    r_true, t_true = truth.relative(first, second)
    err = np.concatenate([to_rvec(rot @ r_true.T), t - t_true])
    sd = np.sqrt(np.diag(rig.camera(second).covariance))
    return err / sd


def test_two_cameras_recover_extrinsics_within_3_sigma(stereo_maps_fit) -> None:
    fit = stereo_maps_fit
    rig = fit.result.rig
    z = _normalized_errors(rig, fit.truth, "A", "B")
    assert np.all(np.abs(z) < 3.0), z
    sig = rig.camera("B").sigma()
    assert 0 < sig["translation_mm"] < 0.2 and 0 < sig["rotation_mrad"] < 1.0
    assert 0.7 < fit.result.stats["reduced_chi2"] < 1.4
    assert np.allclose(rig.camera("A").covariance, 0) and np.allclose(rig.camera("A").rotation,
                                                                       np.eye(3))
    # the held-out view, posed from camera A alone, is predicted in B within its noise
    (held,) = fit.result.stats["heldout"]
    assert held["anchor"] == "A" and 0.5 < held["cameras"]["B"]["whitened_rms"] < 1.6


def test_wrong_extrinsics_fail_the_heldout_view(stereo_maps_fit) -> None:
    """The held-out score sees a 1 mm error in the baseline (so it can fail)."""
    fit = stereo_maps_fit
    rig = fit.result.rig
    models = {c: rig.camera(c).model for c in rig.cameras}
    extr = {c: (rig.camera(c).rotation, rig.camera(c).translation) for c in rig.cameras}
    shifted = dict(extr, B=(extr["B"][0], extr["B"][1] + np.array([1.0, 0.0, 0.0])))
    blocks = [heldout_block(i, models[i.camera], SCREEN, 600, None)
              for i in fit.inputs if i.view == "v6"]
    good = score_view("v6", blocks, models, extr, ["A", "B"])
    bad = score_view("v6", blocks, models, shifted, ["A", "B"])
    assert bad["cameras"]["B"]["whitened_rms"] > 5 * good["cameras"]["B"]["whitened_rms"]


def _chain_truth() -> RigTruth:
    """A, B, C in a row 180 mm apart and turned apart, so A and C see no screen together."""
    poses = {"A": camera_at((0.0, 0.0, 0.0), yaw_deg=12.0), "B": camera_at((180.0, 0.0, 0.0)),
             "C": camera_at((360.0, 0.0, 0.0), yaw_deg=-12.0)}
    return RigTruth({c: mild_pinhole(320, 240) for c in poses},
                    {c: p[0] for c, p in poses.items()}, {c: p[1] for c, p in poses.items()})


def _observation_inputs(truth, groups, per_group, rng, *, state_sigma=True):
    pts = grid_points(SCREEN, 11, 8)
    inputs = []
    for k, (group, view) in enumerate(shared_views(truth, SCREEN, groups, per_group, rng,
                                                   distance_mm=(300.0, 450.0))):
        inputs += [RigInput(c, f"v{k}", observations=view_observations(
            truth, c, view, pts, sigma_px=0.1, rng=rng, state_sigma=state_sigma))
            for c in group]
    return inputs


def test_three_cameras_tied_through_a_chain_of_views() -> None:
    rng = np.random.default_rng(11)
    truth = _chain_truth()
    inputs = _observation_inputs(truth, [("A", "B"), ("B", "C")], 5, rng, state_sigma=False)
    assert not ({i.view for i in inputs if i.camera == "A"}
                & {i.view for i in inputs if i.camera == "C"})
    result = calibrate_rig(inputs, "opencv5", reference="A")
    z = _normalized_errors(result.rig, truth, "A", "C")
    assert np.all(np.abs(z) < 3.0), z
    assert 0.05 < result.stats["estimated_sigma_px"]["A"] < 0.2  # the 0.1 px noise, estimated


def test_disconnected_cameras_are_refused_naming_the_groups() -> None:
    rng = np.random.default_rng(12)
    truth = _chain_truth()
    inputs = _observation_inputs(truth, [("A", "B")], 3, rng)
    inputs += [RigInput("C", f"w{k}", observations=i.observations)
               for k, i in enumerate(inputs) if i.camera == "B"]
    with pytest.raises(ValueError, match=r"not connected.*groups: A, B \| C"):
        calibrate_rig(inputs, "opencv5")
