"""Exports of a rig model: any single-camera format for one camera (mrcal's .cameramodel with
the camera's extrinsics), a camera pair as OpenCV stereo terms or rectification maps, and
the cameras' poses as ROS transforms."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibration.export import opencv_stereo_text, ros_rig_transforms_yaml
from calibration.formats import FORMATS, ExportOptions, export_bytes
from calibration.models.base import ModelError
from calibration.mrcal_io import cameramodel_text
from calibration.shared.rig_model import RigModel
from calibration.undistort import stereo_rectify

PAIR_FORMATS = ("opencv-stereo", "stereo-remap")
RIG_FORMATS = (*PAIR_FORMATS, "ros-transforms")
STEREO_REMAP_FORMAT = "phasecal.stereo-remap/1"
RIG_FILE_NAMES = {"opencv-stereo": "stereo.yaml", "stereo-remap": "stereo_remap.npz",
                  "ros-transforms": "transforms.yaml"}
RIG_MEDIA_TYPES = {"opencv-stereo": "application/x-yaml",
                   "stereo-remap": "application/octet-stream",
                   "ros-transforms": "application/x-yaml"}


def stereo_remap_npz(rig: RigModel, first: str, second: str) -> tuple[bytes, dict[str, Any]]:
    """NPZ: map1_x, map1_y, map2_x, map2_y (float32, for cv2.remap), R1, R2, P1, P2, Q and a
    JSON meta (format, cameras, image size, method)."""
    rot, t = rig.relative(first, second)
    rect = stereo_rectify(rig.camera(first).model, rig.camera(second).model, rot, t)
    seen = [float(np.mean(np.isfinite(rect[f"map{i}_x"]) & (rect[f"map{i}_x"] >= -0.5)
                          & (rect[f"map{i}_x"] <= rig.camera(c).model.image_size[0] - 0.5)))
            for i, c in ((1, first), (2, second))]
    info = {"method": rect["method"], "cameras": [first, second], "seen_fraction": min(seen),
            "image_size": list(rect["image_size"])}
    buf = io.BytesIO()
    np.savez(buf, **{k: v for k, v in rect.items() if isinstance(v, np.ndarray)},
             meta=np.array(json.dumps({"format": STEREO_REMAP_FORMAT, **info})))
    return buf.getvalue(), info


def rig_export_bytes(rig: RigModel, fmt: str, *, camera: str | None = None,
                     cameras: tuple[str, str] | None = None, opts: ExportOptions | None = None
                     ) -> tuple[bytes, dict[str, Any]]:
    """The file of `fmt`: a single-camera format needs `camera`, a pair format `cameras`."""
    opts = opts or ExportOptions()
    if fmt in PAIR_FORMATS:
        if cameras is None or len(cameras) != 2:
            raise ModelError(f"format {fmt}: name two cameras (--cameras A,B)")
        if fmt == "opencv-stereo":
            return opencv_stereo_text(rig, *cameras).encode(), {"exact": True}
        return stereo_remap_npz(rig, *cameras)
    if fmt == "ros-transforms":
        return ros_rig_transforms_yaml(rig).encode(), {"exact": True}
    if fmt not in FORMATS:
        raise ModelError(f"format: expected one of {', '.join((*FORMATS, *RIG_FORMATS))}, "
                         f"got {fmt!r}")
    if camera is None:
        raise ModelError(f"format {fmt}: a rig holds several cameras; name one (--camera), one "
                         f"of {sorted(rig.cameras)}")
    cam = rig.camera(camera)
    if fmt == "mrcal":
        rt = np.concatenate([cv2.Rodrigues(cam.rotation)[0].ravel(), cam.translation])
        text, info = cameramodel_text(cam.model, approximate=opts.approximate,
                                      nx=opts.spline_nx, extrinsics=rt)
        return text.encode(), info
    if fmt == "ros" and opts.camera_name == ExportOptions().camera_name:
        opts = ExportOptions(**{**opts.__dict__, "camera_name": camera})
    return export_bytes(cam.model, fmt, opts)


def export_rig(rig: RigModel, fmt: str, path: str | Path, **kwargs: Any) -> dict[str, Any]:
    """Write `rig_export_bytes` to `path`; returns the info dict."""
    data, info = rig_export_bytes(rig, fmt, **kwargs)
    Path(path).write_bytes(data)
    return info
