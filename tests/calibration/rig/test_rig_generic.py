"""Generic and fisheye cameras in a rig: a raygrid camera held at its own rays, scored by a
held-out view; rectification maps of a pinhole + fisheye pair built through the models."""

from __future__ import annotations

import numpy as np

from calibration.fit.rig.calibrate import calibrate_rig
from calibration.models.parametric import FisheyeModel, OpenCV5Model
from calibration.undistort import stereo_rectify
from hw_mocks.cameras import mild_pinhole
from hw_mocks.fisheye_camera import wide_fisheye
from hw_mocks.rig_truth import camera_at
from tests.calibration.rig.conftest import SCREEN


def test_generic_camera_keeps_its_rays_and_passes_a_heldout_view(stereo_maps_fit) -> None:
    inputs = stereo_maps_fit.inputs
    result = calibrate_rig(inputs, {"A": "opencv5", "B": "raygrid"},
                           SCREEN, options={"max_points_per_view": 400},
                           heldout_views=["v6"])
    assert result.stats["intrinsics_fixed"] == ["B"]
    assert 0.7 < result.stats["reduced_chi2"] < 1.4
    (held,) = result.stats["heldout"]
    assert 0.6 < held["cameras"]["B"]["whitened_rms"] < 1.6
    assert held["cameras"]["B"]["rms_mm"] < 0.1  # the miss on the screen, mm


def test_pinhole_fisheye_rectification_maps_follow_the_models() -> None:
    pin, fish = mild_pinhole(320, 240), wide_fisheye(320, 240, 150.0)
    m1 = OpenCV5Model((320, 240), pin.camera_matrix, np.asarray(pin.dist))
    k = np.array([[fish.f, 0, fish.cx], [0, fish.f, fish.cy], [0, 0, 1.0]])
    m2 = FisheyeModel((320, 240), k, np.asarray(fish.k))
    r_ref, t_ref = camera_at((150.0, 0.0, 0.0), yaw_deg=-8.0)
    rect = stereo_rectify(m1, m2, r_ref, t_ref)
    assert rect["method"] == "unprojected"
    x = np.array([[40.0, 15.0, 500.0], [-30.0, -20.0, 400.0]])
    for i, (model, pts) in enumerate(((m1, x), (m2, x @ r_ref.T + t_ref)), start=1):
        r, p = rect[f"R{i}"], rect[f"P{i}"]
        h = (pts @ r.T) @ p[:3, :3].T
        uv = h[:, :2] / h[:, 2:]
        got = np.column_stack([_bilinear(rect[f"map{i}_x"], uv), _bilinear(rect[f"map{i}_y"], uv)])
        assert np.allclose(got, model.project(pts), atol=0.05), i
        if i == 1:
            rows = uv[:, 1]
        else:
            assert np.allclose(uv[:, 1], rows, atol=1e-6)  # one row in both images


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    u0, v0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
    return ((1 - fu) * (1 - fv) * img[v0, u0] + fu * (1 - fv) * img[v0, u0 + 1]
            + (1 - fu) * fv * img[v0 + 1, u0] + fu * fv * img[v0 + 1, u0 + 1])
