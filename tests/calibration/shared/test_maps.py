"""Decoded maps NPZ: round trip, atomic save, and clear errors for corrupt or foreign files."""

import numpy as np
import pytest

from calibration.shared.maps import MAPS_FORMAT, DecodedMaps, MapsError, load_maps, save_maps


def _maps(h=4, w=5):
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 100, (h, w))
    return DecodedMaps(
        x=x, y=x + 1, sigma_x=np.full((h, w), 0.1, np.float32),
        sigma_y=np.full((h, w), 0.2, np.float32), mask=np.ones((h, w), bool),
        modulation_x=np.ones((h, w), np.float32), modulation_y=np.ones((h, w), np.float32),
        blur_x=np.zeros((h, w), np.float32), blur_y=None,
        meta={"format": MAPS_FORMAT, "pose": "p0"},
    )


def test_round_trip(tmp_path):
    path = tmp_path / "m.npz"
    save_maps(_maps(), path)
    got = load_maps(path)
    assert np.array_equal(got.x, _maps().x) and got.blur_y is None
    assert got.meta["pose"] == "p0" and got.valid_count() == 20
    assert [p.name for p in tmp_path.iterdir()] == ["m.npz"]  # no temp file left behind


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"garbage", "not an NPZ file"),
        (b"", "not an NPZ file"),
        (b"PK\x03\x04broken", "not a readable NPZ file"),
    ],
)
def test_corrupt_bytes_rejected(data, message):
    with pytest.raises(MapsError, match=message):
        load_maps(data)


def test_missing_keys_and_wrong_format(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, x=np.zeros((2, 2)))
    with pytest.raises(MapsError, match="missing keys"):
        load_maps(path)
    m = _maps()
    m.meta = {"format": "other/1"}
    assert load_maps(m.to_npz_bytes()).meta["format"] == MAPS_FORMAT  # writer always stamps it
    m.sigma_x = np.zeros((3, 3), np.float32)
    with pytest.raises(MapsError, match="sigma_x: shape"):
        m.validate()


def test_missing_file():
    with pytest.raises(MapsError, match="not found"):
        load_maps("/nonexistent/maps.npz")


def test_stored_npz_matches_numpy_savez_member_for_member(tmp_path):
    """The direct writer (no chunk copies) gives what np.savez gives: same members, dtypes,
    shapes and values, also for non-contiguous arrays; members stored, not deflated."""
    import io
    import zipfile

    m = _maps(6, 7)
    m.x = np.asfortranarray(m.x)  # not C-contiguous
    m.modulation_y = np.ones((7, 6), np.float32).T  # a transposed view
    save_maps(m, tmp_path / "direct.npz")
    reference = io.BytesIO()
    np.savez(reference, **m.npz_arrays())
    reference.seek(0)
    with np.load(tmp_path / "direct.npz") as got, np.load(reference) as want:
        assert got.files == want.files
        for key in want.files:
            assert got[key].dtype == want[key].dtype and got[key].shape == want[key].shape
            assert got[key].tobytes() == want[key].tobytes(), key
    with zipfile.ZipFile(tmp_path / "direct.npz") as zf:
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_STORED}
        assert zf.testzip() is None  # CRCs right
    small = io.BytesIO()
    m.write_npz(small, compress=True)
    with zipfile.ZipFile(io.BytesIO(small.getvalue())) as zf:
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_DEFLATED}
