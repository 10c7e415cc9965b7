"""sGCC cameras in a rig fitted from decoded maps: each keeps the spline of its own dense fit,
and the extrinsics' covariance carries that spline's uncertainty (the "consider"
covariance), which equals the joint fit's marginal had the spline been fitted with it; the
same rig through `phasecal calibrate --maps`."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from acquisition.patterns import build_plan
from api.cli import main
from calibration.fit.correspondences import point_set, subsample
from calibration.fit.rig.blocks import maps_pixel_block
from calibration.fit.rig.calibrate import calibrate_rig
from calibration.fit.rig.problem import RigCameraState, RigProblem
from calibration.fit.rig.result import RigResult
from calibration.fit.rig.transforms import compose
from calibration.models.sgcc import SGCCBase
from calibration.report_rig import held_rays_note
from calibration.shared.maps import save_maps
from calibration.shared.plan import write_plan
from tests.calibration.rig.conftest import SCREEN, SimulatedRigFit, extrinsics_z, gauge_frame


@pytest.fixture(scope="module")
def sgcc_maps_fit(stereo_maps_fit: SimulatedRigFit) -> RigResult:
    """The shared pair's decoded maps, A fitted as sgcc and B as sgcc-noncentral (v6 held
    out)."""
    return calibrate_rig(stereo_maps_fit.inputs, {"A": "sgcc", "B": "sgcc-noncentral"}, SCREEN,
                         options={"max_points_per_view": 600}, heldout_views=["v6"])


def test_held_splines_enter_the_extrinsics_covariance(stereo_maps_fit: SimulatedRigFit,
                                                      sgcc_maps_fit: RigResult) -> None:
    st = sgcc_maps_fit.stats
    assert st["intrinsics_fixed"] == ["A", "B"]
    assert st["intrinsics_rays_in_covariance"] == ["A", "B"]
    assert sgcc_maps_fit.rig.stats["intrinsics_rays_in_covariance"] == ["A", "B"]  # kept
    note = held_rays_note(st)
    assert "A, B kept the rays" in note and "includes" in note and "lower bound" not in note
    raygrid = held_rays_note({"intrinsics_fixed": ["A", "B"],
                              "intrinsics_rays_in_covariance": ["A"]})
    assert "A kept" in raygrid and "B kept" in raygrid and "lower bound" in raygrid
    assert st["converged"] and 0.7 < st["reduced_chi2"] < 1.4
    truth = stereo_maps_fit.truth
    frames = {c: gauge_frame(truth.cameras[c]) for c in "AB"}
    assert np.all(np.abs(extrinsics_z(sgcc_maps_fit.rig, truth, frames)) < 3.0)
    (held,) = st["heldout"]
    assert 0.6 < held["cameras"]["B"]["whitened_rms"] < 1.6


def test_held_spline_share_is_the_joint_marginal(stereo_maps_fit: SimulatedRigFit,
                                                 sgcc_maps_fit: RigResult) -> None:
    """A held spline whose covariance is its marginal in the fit that moves it gives the
    extrinsics and view poses that fit's covariance (the block-inverse identity), and more
    than holding it without its uncertainty. (Each camera's share is added on its own:
    right for splines from independent single-camera fits, whose errors are uncorrelated.)"""
    rig, poses = sgcc_maps_fit.rig, sgcc_maps_fit.view_poses
    ext = {c: (rig.camera(c).rotation, rig.camera(c).translation) for c in "AB"}
    views = list(poses)
    held = {c: copy.deepcopy(rig.camera(c).model) for c in "AB"}
    for m in held.values():
        m.covariance = None  # held without its uncertainty: the old lower bound
    blocks = [maps_pixel_block(i.camera, i.view, held[i.camera],
                               compose(ext[i.camera], poses[i.view]),
                               subsample(point_set(i.maps, SCREEN), 150))
              for i in stereo_maps_fit.inputs if i.view in poses]
    assert {b.kind for b in blocks} == {"spline"}

    def state(model: SGCCBase, moves: bool) -> RigCameraState:
        return RigCameraState.of(model, np.full(model.get_params().size, moves))

    moved_b = state(copy.deepcopy(held["B"]), True)  # B's spline in the fit, A's held
    joint = RigProblem({"A": state(held["A"], False), "B": moved_b}, "A", views, blocks)
    cov_joint, chi2_joint = joint.covariance(joint.pack(ext, poses))
    problem = RigProblem({c: state(m, False) for c, m in held.items()}, "A", views, blocks)
    x = problem.pack(ext, poses)
    cov_bare, chi2 = problem.covariance(x)
    idx = joint.intrinsics["B"]
    assert moved_b.gauge is not None
    held["B"].covariance = moved_b.gauge.expand_matrix(cov_joint[np.ix_(idx, idx)]) * (
        chi2 / chi2_joint)  # the data term of each covariance scales with its chi-square
    cov, _ = problem.covariance(x)

    others = np.concatenate([joint.extrinsics["B"], *(joint.poses[v] for v in views)])
    np.testing.assert_allclose(cov * chi2_joint / chi2, cov_joint[np.ix_(others, others)],
                               rtol=1e-6)
    ratio = np.sqrt(np.diag(cov)[:6] / np.diag(cov_bare)[:6])  # B's extrinsics
    assert ratio.min() >= 1.0 and ratio.max() > 3.0, ratio


def test_the_cli_writes_the_same_rig(stereo_maps_fit: SimulatedRigFit, sgcc_maps_fit: RigResult,
                                     tmp_path: Path) -> None:
    """`phasecal calibrate --maps` of the same files and models: the rig file carries the
    extrinsics' covariance with the splines' share, and the statistics name those cameras."""
    plan = build_plan(SCREEN.width_px, SCREEN.height_px, SCREEN.pitch_mm)
    write_plan(plan, tmp_path / "plan.json")
    args = []
    for i in stereo_maps_fit.inputs:
        assert i.maps is not None
        save_maps(i.maps, tmp_path / f"{i.camera}{i.view}.npz")
        args.append(f"{i.camera}/{i.view}={tmp_path / f'{i.camera}{i.view}.npz'}")
    out = tmp_path / "rig.json"
    assert main(["calibrate", "--plan", str(tmp_path / "plan.json"), "--maps", *args,
                 "--model", "sgcc", "--model", "B=sgcc-noncentral", "--heldout-view", "v6",
                 "--option", "max_points_per_view=600", "-o", str(out)]) == 0
    ext = json.loads(out.read_text())["cameras"]["B"]["extrinsics"]
    np.testing.assert_allclose(ext["covariance"], sgcc_maps_fit.rig.camera("B").covariance,
                               rtol=1e-6, atol=1e-15)
    stats = json.loads(out.with_name("rig.result.json").read_text())["stats"]
    assert stats["intrinsics_rays_in_covariance"] == ["A", "B"]
