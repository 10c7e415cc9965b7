"""Export pinhole-family models: OpenCV FileStorage YAML (cv2.FileStorage) and ROS camera_info;
for a rig, a camera pair as cv2.stereoCalibrate's terms and the cameras' poses as ROS transforms.

Both are exact or refused: a model with terms the format cannot carry raises `ModelError`
naming them (never silently truncated).
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from calibration.models.base import CameraModel, ModelError
from calibration.models.parametric import PinholeFamily
from calibration.shared.rig_model import RigModel

_ROS_MODELS = {"opencv5": "plumb_bob", "opencv-rational": "rational_polynomial",
               "fisheye": "equidistant"}


def _pinhole(model: CameraModel, what: str) -> PinholeFamily:
    """The model as a pinhole-family model, or a clear error naming the format."""
    if not isinstance(model, PinholeFamily):
        raise ModelError(f"{what}: model type {model.type_name!r} has no camera_matrix/"
                         f"distortion form; export supports {sorted(_ROS_MODELS)}")
    return model


def opencv_yaml_text(model: CameraModel) -> str:
    """FileStorage YAML: model_type, image size, camera_matrix, distortion_coefficients (1xN).

    `model_type` fisheye means the 4 coefficients are cv2.fisheye's (k1..k4), for
    cv2.fisheye.initUndistortRectifyMap; otherwise they are in cv2's own order (5 or 12).
    """
    m = _pinhole(model, "OpenCV export")
    fs = cv2.FileStorage("out.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.write("model_type", m.type_name)
    fs.write("image_width", int(m.image_size[0]))
    fs.write("image_height", int(m.image_size[1]))
    fs.write("camera_matrix", m.camera_matrix)
    fs.write("distortion_coefficients", m.dist.reshape(1, -1))
    return fs.releaseAndGetString()


def export_opencv_yaml(model: CameraModel, path: str | Path) -> None:
    """Write `opencv_yaml_text` to a file."""
    Path(path).write_text(opencv_yaml_text(model), encoding="utf-8")


def opencv_yaml_model_type(path: str | Path, n_dist: int) -> str:
    """Phasecal model type of an OpenCV YAML: its model_type, else from the coefficient count."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        kind = fs.getNode("model_type").string()
    finally:
        fs.release()
    if kind:
        if kind not in _ROS_MODELS:
            raise ModelError(f"{path}: model_type {kind!r}: expected one of {sorted(_ROS_MODELS)}")
        return kind
    if n_dist in (4, 5):
        return "opencv5"
    if n_dist in (8, 12):
        return "opencv-rational"
    raise ModelError(f"{path}: distortion_coefficients: {n_dist} values; expected 4, 5, 8 or 12")


def read_opencv_yaml(path: str | Path) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Read back (K, distortion, (W, H)) from an `export_opencv_yaml` file."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        k = fs.getNode("camera_matrix").mat()
        d = fs.getNode("distortion_coefficients").mat()
        size = (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real()))
    finally:
        fs.release()
    if k is None or d is None:
        raise ModelError(f"{path}: missing camera_matrix or distortion_coefficients")
    return k, d.ravel(), size


_ROS_NAME = re.compile(r"^[A-Za-z0-9_]+$")


def ros_camera_info_yaml(model: CameraModel, camera_name: str = "camera") -> str:
    """ROS camera_info YAML text (camera_calibration_parsers layout) for a pinhole-family model.

    Monocular: R = I and P = [K | 0] (the rectified image keeps K). Thin-prism terms have no
    ROS distortion model: a model with nonzero s1..s4 is refused.
    """
    m = _pinhole(model, "ROS export")
    if not _ROS_NAME.match(camera_name):
        raise ModelError(f"camera_name: expected letters, digits and '_' (ROS "
                         f"camera_info_manager's rule), got {camera_name!r}")
    w, h = m.image_size
    k = m.camera_matrix
    d = m.dist
    if m.type_name == "opencv-rational":
        if np.any(d[8:] != 0):
            raise ModelError(
                "ROS export: the model has thin-prism terms s1..s4 = "
                f"{[float(v) for v in d[8:]]}, which no ROS distortion_model carries "
                "(rational_polynomial has k1..k6, p1, p2); refusing to drop them. Refit "
                "without them, or use format opencv-yaml or mrcal (OPENCV12)")
        d = d[:8]
    p = np.hstack([k, np.zeros((3, 1))])

    def mat(rows: int, cols: int, data: np.ndarray) -> str:
        vals = ", ".join(repr(float(v)) for v in np.ravel(data))
        return f"\n  rows: {rows}\n  cols: {cols}\n  data: [{vals}]"

    return (f"image_width: {w}\nimage_height: {h}\ncamera_name: {camera_name}\n"
            f"camera_matrix:{mat(3, 3, k)}\n"
            f"distortion_model: {_ROS_MODELS[m.type_name]}\n"
            f"distortion_coefficients:{mat(1, d.size, d)}\n"
            f"rectification_matrix:{mat(3, 3, np.eye(3))}\n"
            f"projection_matrix:{mat(3, 4, p)}\n")


def export_ros_yaml(model: CameraModel, path: str | Path, camera_name: str = "camera") -> None:
    """Write ROS camera_info YAML."""
    Path(path).write_text(ros_camera_info_yaml(model, camera_name), encoding="utf-8")


def _stereo_pair(rig: RigModel, first: str, second: str) -> tuple[PinholeFamily, PinholeFamily]:
    """The two cameras' OpenCV-family models, or ModelError naming what cannot be carried."""
    if first == second:
        raise ModelError(f"cameras: expected two different cameras, got {first!r} twice")
    models = []
    for name in (first, second):
        m = rig.camera(name).model
        if not isinstance(m, PinholeFamily):
            raise ModelError(f"opencv-stereo: camera {name} is a {m.type_name!r} model, which "
                             f"OpenCV cannot carry; export supports {sorted(_ROS_MODELS)}")
        models.append(m)
    kinds = {m.type_name == "fisheye" for m in models}
    if len(kinds) > 1:
        raise ModelError("opencv-stereo: one fisheye and one pinhole camera have no common "
                         "OpenCV stereo model (cv2.stereoRectify or cv2.fisheye.stereoRectify); "
                         "use format stereo-remap for rectification maps")
    return models[0], models[1]


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def opencv_stereo_text(rig: RigModel, first: str, second: str) -> str:
    """FileStorage YAML of a camera pair in cv2.stereoCalibrate's terms: K1, D1, K2, D2, R, T
    (X2 = R X1 + T, mm), E, F, image_size_1/2 and each camera's model_type (fisheye: D are
    cv2.fisheye's k1..k4)."""
    m1, m2 = _stereo_pair(rig, first, second)
    rot, t = rig.relative(first, second)
    e = _skew(t) @ rot
    f = np.linalg.inv(m2.camera_matrix).T @ e @ np.linalg.inv(m1.camera_matrix)
    fs = cv2.FileStorage("out.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.write("camera_1", first)
    fs.write("camera_2", second)
    fs.write("model_type_1", m1.type_name)
    fs.write("model_type_2", m2.type_name)
    fs.write("image_size_1", np.array(m1.image_size, dtype=np.int32).reshape(1, 2))
    fs.write("image_size_2", np.array(m2.image_size, dtype=np.int32).reshape(1, 2))
    fs.write("K1", m1.camera_matrix)
    fs.write("D1", m1.dist.reshape(1, -1))
    fs.write("K2", m2.camera_matrix)
    fs.write("D2", m2.dist.reshape(1, -1))
    fs.write("R", rot)
    fs.write("T", t.reshape(3, 1))
    fs.write("E", e)
    fs.write("F", f / f[2, 2] if abs(f[2, 2]) > 1e-300 else f)
    return fs.releaseAndGetString()


def ros_rig_transforms_yaml(rig: RigModel) -> str:
    """Each other camera's pose in the reference camera's optical frame, as tf2 static transforms
    (parent = reference, child = camera; translation in metres, rotation as x, y, z, w)."""
    lines = [f"reference: {rig.reference}", "transforms:"]
    for name, cam in rig.cameras.items():
        if name == rig.reference:
            continue
        if not _ROS_NAME.match(name):
            raise ModelError(f"camera name {name!r}: ROS frame names need letters, digits, '_'")
        rot_c2r = cam.rotation.T  # camera axes in the reference frame
        pos = -rot_c2r @ cam.translation / 1000.0
        q = Rotation.from_matrix(rot_c2r).as_quat()
        lines += [f"  - parent_frame: {rig.reference}_optical", f"    child_frame: {name}_optical",
                  f"    translation: [{', '.join(repr(float(v)) for v in pos)}]",
                  f"    rotation: [{', '.join(repr(float(v)) for v in q)}]"]
    return "\n".join(lines) + "\n"
