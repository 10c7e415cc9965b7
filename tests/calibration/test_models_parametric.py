"""Parametric models: agreement with hw_mocks ground truth, round trips, JSON I/O, export."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.export import export_opencv_yaml, read_opencv_yaml, ros_camera_info_yaml
from calibration.models.base import ModelError, jsonable, load_model, model_types, save_model
from calibration.models.parametric import FisheyeModel, OpenCV5Model, OpenCVRationalModel
from hw_mocks.cameras import PinholeCamera, mild_pinhole, wide_fisheye


def _from_truth_pinhole(cam: PinholeCamera) -> OpenCV5Model:
    """Our opencv5 model with the truth camera's parameters."""
    return OpenCV5Model((cam.width, cam.height), cam.camera_matrix, np.asarray(cam.dist))


def _fisheye_model():
    """Truth fisheye and our fisheye model with its parameters."""
    cam = wide_fisheye(fov_deg=150)
    k = np.array([[cam.f, 0, cam.cx], [0, cam.f, cam.cy], [0, 0, 1.0]])
    return cam, FisheyeModel((cam.width, cam.height), k, np.asarray(cam.k))


def _rational() -> OpenCVRationalModel:
    """A rational model with thin prism terms, monotonic over the image."""
    k = np.array([[500.0, 0, 330], [0, 502, 236], [0, 0, 1]])
    d = [0.3, -0.05, 1e-3, -5e-4, 0.01, 0.45, 0.02, 0.005, 1e-3, -2e-4, 5e-4, 1e-4]
    return OpenCVRationalModel((640, 480), k, np.array(d))


def _grid(w: int, h: int, step: int = 2) -> np.ndarray:
    """Pixel grid covering the whole image, edges included."""
    u, v = np.meshgrid(np.r_[np.arange(0, w, step), w - 1.0], np.r_[np.arange(0, h, step), h - 1.0])
    return np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)


def test_registered() -> None:
    assert {"opencv5", "opencv-rational", "fisheye"} <= set(model_types())


def test_opencv5_matches_truth_projection() -> None:
    cam = mild_pinhole()
    model = _from_truth_pinhole(cam)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-300, 300, (500, 2)), rng.uniform(500, 900, 500)])
    want = cam.project(pts)
    got = model.project(pts)
    ok = np.all(np.isfinite(want), axis=1)
    assert ok.sum() > 200
    np.testing.assert_allclose(got[ok], want[ok], atol=1e-9)


def test_fisheye_matches_truth_projection_and_rays() -> None:
    cam, model = _fisheye_model()
    pix = _grid(cam.width, cam.height, 8)
    _, d_true = cam.rays(pix[:, 0], pix[:, 1])
    _, d = model.unproject(pix)
    ok = np.all(np.isfinite(d_true), axis=1)
    np.testing.assert_allclose(d[ok], d_true[ok], atol=1e-9)
    # The image edge sees rays ~75 degrees off axis (150-degree lens).
    assert np.degrees(np.arccos(d[ok, 2].min())) > 74.0


@pytest.mark.parametrize("which", ["opencv5", "opencv-rational", "fisheye"])
def test_project_unproject_round_trip_whole_image(which: str) -> None:
    if which == "opencv5":
        model = _from_truth_pinhole(mild_pinhole())
    elif which == "fisheye":
        model = _fisheye_model()[1]
    else:
        model = _rational()
    pix = _grid(*model.image_size)
    origins, d = model.unproject(pix)
    assert np.all(np.isfinite(d)), "every pixel of the image must have a ray"
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert np.all(origins == 0)
    back = model.project(d * 1000.0)
    assert np.max(np.abs(back - pix)) < 1e-6


def test_json_round_trip(tmp_path) -> None:
    model = _rational()
    model.stats = {"rms_px": 0.1}
    path = tmp_path / "m.json"
    save_model(model, path)
    loaded = load_model(path)
    assert isinstance(loaded, OpenCVRationalModel)
    np.testing.assert_array_equal(loaded.get_params(), model.get_params())
    assert loaded.stats == {"rms_px": 0.1}


@pytest.mark.parametrize(
    ("mutate", "needle"),
    [
        (lambda d: d["params"].pop("camera_matrix"), "camera_matrix"),
        (lambda d: d["params"].__setitem__("distortion", [0.1, 0.2]), "distortion"),
        (lambda d: d["params"].__setitem__("distortion", ["a"] * 5), "distortion"),
        (lambda d: d["params"]["camera_matrix"].__setitem__(0, [-5, 0, 1]), "camera_matrix"),
        (lambda d: d.__setitem__("type", "nonesuch"), "type"),
    ],
)
def test_corrupt_model_files(tmp_path, mutate, needle: str) -> None:
    doc = _from_truth_pinhole(mild_pinhole()).to_dict()
    mutate(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelError, match=needle):
        load_model(path)


def test_not_json(tmp_path) -> None:
    path = tmp_path / "bad.json"
    path.write_text("{not json")
    with pytest.raises(ModelError, match="not valid JSON"):
        load_model(path)


def test_opencv_and_ros_export(tmp_path) -> None:
    model = _from_truth_pinhole(mild_pinhole())
    path = tmp_path / "cam.yaml"
    export_opencv_yaml(model, path)
    k, d, size = read_opencv_yaml(path)
    np.testing.assert_allclose(k, model.camera_matrix)
    np.testing.assert_allclose(d, model.dist)
    assert size == model.image_size
    text = ros_camera_info_yaml(model, "cam0")
    assert "distortion_model: plumb_bob" in text and "camera_name: cam0" in text
    assert "image_width: 640" in text
    assert "equidistant" in ros_camera_info_yaml(_fisheye_model()[1])


def test_jsonable_gives_strict_json_for_numpy_statistics() -> None:
    stats = {1: np.float32(2.5), "per_pixel": np.array([np.nan, 1.0]), "n": (np.int64(3),),
             "worst": np.float64(np.inf)}
    plain = jsonable(stats)
    assert plain == {"1": 2.5, "per_pixel": [None, 1.0], "n": [3], "worst": None}
    assert json.loads(json.dumps(plain, allow_nan=False)) == plain
