"""The rig model file (phasecal.rig/1): round trip, reference frame, validation errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.shared.rig_model import RigModelError, load_rig, rig_from_dict, save_rig


def test_round_trip_keeps_models_extrinsics_and_covariance(stereo_maps_fit, tmp_path) -> None:
    rig = stereo_maps_fit.result.rig
    save_rig(rig, tmp_path / "rig.json")
    back = load_rig(tmp_path / "rig.json")
    assert back.reference == "A" and sorted(back.cameras) == ["A", "B"]
    b, b2 = rig.camera("B"), back.camera("B")
    assert np.allclose(b2.rotation, b.rotation, atol=1e-12)
    assert np.allclose(b2.translation, b.translation) and np.allclose(b2.covariance, b.covariance)
    assert np.allclose(b2.model.get_params(), b.model.get_params())
    # a point in the reference frame projects into B and comes back on B's ray (ref frame)
    p = np.array([[30.0, -10.0, 450.0]])
    o, d = b2.unproject(b2.project(p))
    assert np.linalg.norm(np.cross(p - o, d)) < 1e-6


def test_a_rotation_below_ten_microradians_survives_the_round_trip(stereo_maps_fit) -> None:
    """A near-parallel pair's relative rotation can be smaller than 1e-5 rad (a dense fit's
    sigma is a few microradians): the loader keeps it, not the identity."""
    doc = json.loads(json.dumps(stereo_maps_fit.result.rig.to_dict()))
    rvec = np.array([3e-6, -2e-6, 4e-6])
    rot = Rotation.from_rotvec(rvec).as_matrix()
    doc["cameras"]["B"]["extrinsics"]["R"] = rot.tolist()
    back = rig_from_dict(json.loads(json.dumps(doc))).camera("B").rotation
    assert np.allclose(Rotation.from_matrix(back).as_rotvec(), rvec, rtol=0, atol=1e-12)
    assert np.allclose(back @ back.T, np.eye(3), atol=1e-15)


@pytest.mark.parametrize(("edit", "message"), [
    (lambda d: d.update(format="phasecal.model/1"), "format"),
    (lambda d: d.update(reference="Z"), "reference"),
    (lambda d: d["cameras"]["B"]["extrinsics"].update(R=np.diag([1, 1, -1.0]).tolist()),
     "cameras.B.extrinsics.R"),
    (lambda d: d["cameras"]["B"]["extrinsics"].update(t_mm=[1, 2]), "cameras.B.extrinsics.t_mm"),
    (lambda d: d["cameras"]["A"]["extrinsics"].update(t_mm=[1.0, 0, 0]), "reference camera"),
    (lambda d: d["cameras"]["B"]["model"].update(type="nope"), "cameras.B.model"),
])
def test_malformed_rig_files_are_refused_naming_the_field(stereo_maps_fit, edit, message) -> None:
    doc = json.loads(json.dumps(stereo_maps_fit.result.rig.to_dict()))
    edit(doc)
    with pytest.raises(RigModelError, match=message):
        rig_from_dict(doc)
