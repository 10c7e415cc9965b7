"""Export pinhole-family models: OpenCV FileStorage YAML (cv2.FileStorage) and ROS camera_info."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from calibration.models.base import CameraModel, ModelError
from calibration.models.parametric import PinholeFamily

_ROS_MODELS = {"opencv5": "plumb_bob", "opencv-rational": "rational_polynomial",
               "fisheye": "equidistant"}


def _pinhole(model: CameraModel, what: str) -> PinholeFamily:
    """The model as a pinhole-family model, or a clear error naming the format."""
    if not isinstance(model, PinholeFamily):
        raise ModelError(f"{what}: model type {model.type_name!r} has no camera_matrix/"
                         f"distortion form; export supports {sorted(_ROS_MODELS)}")
    return model


def export_opencv_yaml(model: CameraModel, path: str | Path) -> None:
    """Write camera_matrix, distortion_coefficients, image size and model type via FileStorage."""
    m = _pinhole(model, "OpenCV export")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("model_type", m.type_name)
        fs.write("image_width", int(m.image_size[0]))
        fs.write("image_height", int(m.image_size[1]))
        fs.write("camera_matrix", m.camera_matrix)
        fs.write("distortion_coefficients", m.dist.reshape(1, -1))
    finally:
        fs.release()


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


def ros_camera_info_yaml(model: CameraModel, camera_name: str = "camera") -> str:
    """ROS camera_info YAML text (camera_calibration_parsers layout) for a pinhole-family model."""
    m = _pinhole(model, "ROS export")
    w, h = m.image_size
    k = m.camera_matrix
    d = m.dist if m.type_name != "opencv-rational" else m.dist[:8]
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
