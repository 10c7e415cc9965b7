"""sGCC cameras in a rig fitted from target observations: each starts from its own sparse
sGCC fit, its spline moves in the joint fit, and the extrinsics and rays agree with the
simulated truth within their predicted sigma; mixed with maps and parametric cameras;
raygrid and too few points refused with the reason."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from calibration.fit.rig.calibrate import calibrate_rig
from calibration.fit.rig.inputs import RigInput
from calibration.fit.sparse.crossval import AGREE_RATIO
from calibration.fit.sparse.uncertainty import projection_covariance
from calibration.shared.rig_model import RigModel
from hw_mocks.rig_truth import RigTruth, grid_points, shared_views, view_maps, view_observations
from tests.calibration.rig.conftest import SCREEN, extrinsics_z, gauge_frame, two_pinholes

VIEWS = 8
SIGMA_PX = 0.1


@pytest.fixture(scope="module")
def board_views() -> tuple[RigTruth, list[tuple[str, str, object]], dict]:
    """Two pinholes seeing an 11 x 8 board drawn on the screen in 8 shared views: the
    corners each records (0.1 px noise), and the screen poses for maps of the same views."""
    rng = np.random.default_rng(3)
    truth = two_pinholes()
    board = grid_points(SCREEN, 11, 8)
    obs, poses = [], {}
    for k, (group, view) in enumerate(shared_views(truth, SCREEN, [("A", "B")], VIEWS, rng)):
        poses[f"v{k}"] = view
        for cam in group:
            obs.append((cam, f"v{k}", view_observations(truth, cam, view, board,
                                                        sigma_px=SIGMA_PX, rng=rng)))
    return truth, obs, poses


def _inputs(obs: list, cameras: str = "AB") -> list[RigInput]:
    return [RigInput(c, v, observations=o) for c, v, o in obs if c in cameras]


def _ray_errors(rig: RigModel, truth: RigTruth, name: str, frame: np.ndarray,
                pixels: np.ndarray) -> tuple[float, float]:
    """The truth's rays at `pixels`, turned into the model's frame and projected by the
    fitted model: (RMS of the misses over their predicted sigma per axis, RMS miss px)."""
    model = rig.camera(name).model
    _, d = truth.cameras[name].rays(pixels[:, 0], pixels[:, 1])
    rays = 1000.0 * d @ frame.T
    miss = model.project(rays) - pixels
    cov = projection_covariance(model, model.covariance, rays)
    z2 = np.einsum("ni,nij,nj->n", miss, np.linalg.inv(cov), miss)
    return float(np.sqrt(np.mean(z2) / 2)), float(np.sqrt(np.mean(np.sum(miss**2, axis=1))))


def test_sgcc_rig_from_observations_matches_the_truth(board_views) -> None:
    truth, obs, _ = board_views
    result = calibrate_rig(_inputs(obs), "sgcc")
    st = result.stats
    assert st["intrinsics_fixed"] == [] and st["converged"]
    assert 0.8 < st["reduced_chi2"] < 1.25
    frames = {c: gauge_frame(truth.cameras[c]) for c in "AB"}
    assert np.all(np.abs(extrinsics_z(result.rig, truth, frames)) < 3.0)
    for cam in "AB":
        seen = np.concatenate([o.image_xy[o.used()] for c, _, o in obs if c == cam])
        ratio, rms = _ray_errors(result.rig, truth, cam, frames[cam], seen)
        assert ratio <= AGREE_RATIO and rms < 0.2, (cam, ratio, rms)


def test_mixed_rig_maps_parametric_and_observations_noncentral(board_views) -> None:
    truth, obs, poses = board_views
    rng = np.random.default_rng(11)
    maps = [RigInput("A", v, maps=view_maps(truth, "A", pose, SCREEN, sigma_px=0.05, rng=rng))
            for v, pose in poses.items()]
    result = calibrate_rig(maps + _inputs(obs, "B"), {"A": "opencv5", "B": "sgcc-noncentral"},
                           SCREEN, options={"max_points_per_view": 300})
    st = result.stats
    assert st["intrinsics_fixed"] == [] and st["converged"]
    assert {r["camera"]: r for r in st["per_view"]}["B"]["rms_px"] < 0.2
    # A (opencv5) is in its optical frame, B (non-central sGCC) in its gauge's
    frames = {"A": np.eye(3), "B": gauge_frame(truth.cameras["B"])}
    assert np.all(np.abs(extrinsics_z(result.rig, truth, frames)) < 3.0)


def test_raygrid_and_too_few_points_are_refused_with_the_reason(board_views) -> None:
    _, obs, _ = board_views
    with pytest.raises(ValueError, match=r"camera B: raygrid: a rig fits it from decoded maps "
                                         r"only .*one ray per pixel"):
        calibrate_rig(_inputs(obs), {"A": "opencv5", "B": "raygrid"})
    sparse = np.arange(88) % 3 == 0  # every third corner of three views
    few = [(c, v, dataclasses.replace(o, image_xy=np.where(sparse[:, None], o.image_xy, np.nan)))
           for c, v, o in obs if v in ("v0", "v1", "v2")]
    with pytest.raises(ValueError, match=r"camera A: observations: \d+ points in 3 views are "
                                         r"too few for an sGCC mesh.*add about \d+ view"):
        calibrate_rig(_inputs(few), "sgcc")
