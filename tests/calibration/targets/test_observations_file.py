"""The phasecal.observations/1 NPZ: round trip and clear errors naming the key."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from calibration.shared.observations import (
    ObservationsError,
    TargetObservations,
    load_observations,
    save_observations,
)


def _view() -> TargetObservations:
    xy = np.array([[10.0, 20.0], [30.5, 40.25], [np.nan, np.nan]])
    xyz = np.array([[0.0, 0.0, 0.0], [25.0, 0.0, 0.0], [0.0, 25.0, 0.0]])
    return TargetObservations(xy, xyz, (640, 480), weight=np.array([1.0, 0.5, 1.0]),
                              sigma_px=0.2, meta={"view": "v0"})


def _npz(**arrays: object) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def test_round_trip(tmp_path):
    path = tmp_path / "v0.npz"
    save_observations(_view(), path)
    back = load_observations(path)
    np.testing.assert_array_equal(back.image_xy, _view().image_xy)
    np.testing.assert_array_equal(back.target_xyz, _view().target_xyz)
    assert back.image_size == (640, 480)
    assert back.sigma_px == 0.2
    assert back.meta["view"] == "v0" and back.meta["format"] == "phasecal.observations/1"
    assert back.used().tolist() == [True, True, False]


@pytest.mark.parametrize(("change", "message"), [
    ({"image_xy": np.zeros((3, 3))}, "image_xy: expected shape (N, 2)"),
    ({"target_xyz": np.zeros((2, 3))}, "target_xyz: 2 rows, image_xy has 3"),
    ({"weight": np.ones(2)}, "weight: expected shape (3,)"),
    ({"sigma_px": np.array(-1.0)}, "sigma_px: expected a positive number"),
    ({"image_size": np.array([640.0, 480.0])}, "image_size: expected 2 integers"),
    ({"meta": np.array(json.dumps({"format": "phasecal.maps/1"}))}, "meta.format"),
])
def test_bad_members_are_named(change, message):
    arrays = _view().npz_arrays()
    arrays.update(change)
    with pytest.raises(ObservationsError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_observations(_npz(**arrays))


def test_missing_key_and_not_npz(tmp_path):
    arrays = _view().npz_arrays()
    del arrays["target_xyz"]
    with pytest.raises(ObservationsError, match="missing keys \\['target_xyz'\\]"):
        load_observations(_npz(**arrays))
    bad = tmp_path / "x.npz"
    bad.write_text("hello")
    with pytest.raises(ObservationsError, match="not an NPZ file"):
        load_observations(bad)
    with pytest.raises(ObservationsError, match="not found"):
        load_observations(tmp_path / "missing.npz")
