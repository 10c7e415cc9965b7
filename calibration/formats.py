"""Every export format of every model behind one call (`phasecal export`, REST `/export`), and
`load_model_any` reading a phasecal model JSON, an mrcal .cameramodel or an OpenCV YAML."""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibration import export as opencv_export
from calibration.compare import ray_angle_difference
from calibration.models.base import CameraModel, ModelError, load_model
from calibration.models.parametric import PARAMETRIC_MODELS, PinholeFamily
from calibration.undistort import best_opencv_model, rectify_maps, undistort_points

FORMATS = ("opencv-yaml", "ros", "mrcal", "remap", "opencv-fit")
MEDIA_TYPES = {"opencv-yaml": "application/x-yaml", "ros": "application/x-yaml",
               "mrcal": "text/plain", "remap": "application/octet-stream",
               "opencv-fit": "application/octet-stream"}
FILE_NAMES = {"opencv-yaml": "opencv.yaml", "ros": "camera_info.yaml",
              "mrcal": "camera.cameramodel", "remap": "remap.npz", "opencv-fit": "opencv_fit.npz"}
OPENCV_FIT_FORMAT = "phasecal.opencv-fit/1"
REMAP_FORMAT = "phasecal.remap/1"


@dataclass
class ExportOptions:
    """Format options; each applies to the formats named in its comment."""

    pinhole: tuple[float, float, float, float, int, int] | None = None  # remap
    rotation: np.ndarray | None = None  # remap: virtual-from-model (or -from-align_to) 3x3
    align_to: CameraModel | None = None  # remap: the virtual camera lives in this model's frame
    camera_name: str = "camera"  # ros
    approximate: bool = False  # mrcal: allow the spline fit for the fisheye model
    spline_nx: int = 16  # mrcal: knots across the field of view of the spline fit
    opencv_kind: str = "opencv-rational"  # opencv-fit


def parse_pinhole(text: str) -> tuple[float, float, float, float, int, int]:
    """`FX,FY,CX,CY,W,H` -> tuple (positive focal lengths and size)."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        fx, fy, cx, cy = (float(p) for p in parts[:4])
        w, h = int(parts[4]), int(parts[5])
        if len(parts) != 6:
            raise ValueError
    except (ValueError, IndexError):
        raise ModelError(f"pinhole: expected FX,FY,CX,CY,W,H (6 numbers), got {text!r}") from None
    if not (fx > 0 and fy > 0 and w > 0 and h > 0 and math.isfinite(cx) and math.isfinite(cy)):
        raise ModelError(f"pinhole: expected FX, FY, W, H > 0 and finite CX, CY, got {text!r}")
    return fx, fy, cx, cy, w, h


def parse_rotation(text: str) -> np.ndarray:
    """`RX,RY,RZ` (Rodrigues vector, rad) or 9 numbers (row-major 3x3) -> rotation matrix."""
    try:
        vals = np.array([float(p) for p in str(text).split(",")])
    except ValueError:
        raise ModelError(f"rotation: expected 3 (Rodrigues, rad) or 9 numbers, got {text!r}"
                         ) from None
    if vals.size == 3 and np.all(np.isfinite(vals)):
        return cv2.Rodrigues(vals)[0]
    if vals.size == 9 and np.all(np.isfinite(vals)):
        r = vals.reshape(3, 3)
        if np.allclose(r @ r.T, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0:
            return r
        raise ModelError("rotation: the 3x3 matrix is not a rotation (R R^T != I or det < 0)")
    raise ModelError(f"rotation: expected 3 (Rodrigues, rad) or 9 numbers, got {text!r}")


def virtual_camera(model: CameraModel, opts: ExportOptions) -> tuple[np.ndarray, tuple[int, int]]:
    """(K, (W, H)) of the virtual pinhole: --pinhole, else an OpenCV-family model's own K."""
    if opts.pinhole is not None:
        fx, fy, cx, cy, w, h = opts.pinhole
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), (w, h)
    if isinstance(model, PinholeFamily):
        return model.camera_matrix, model.image_size
    raise ModelError(f"pinhole: required for a {model.type_name!r} model (it has no camera "
                     "matrix); give FX,FY,CX,CY,W,H, e.g. the K of format opencv-fit")


def model_rotation(model: CameraModel, opts: ExportOptions) -> np.ndarray | None:
    """`rectify_maps`' rotation: user rotation, composed with the align_to frame change."""
    if opts.align_to is None:
        return opts.rotation
    if opts.align_to.image_size != model.image_size:
        raise ModelError(f"align_to: image size {list(opts.align_to.image_size)} differs from "
                         f"the model's {list(model.image_size)}")
    # rot: model frame from align_to frame (best rotation between the two ray fields).
    rot = ray_angle_difference(opts.align_to.unproject, model.unproject, model.image_size,
                               step_px=8.0)["rotation"]
    user = np.eye(3) if opts.rotation is None else opts.rotation
    return user @ rot.T


def remap_npz(model: CameraModel, opts: ExportOptions) -> tuple[bytes, dict[str, Any]]:
    """NPZ bytes with float32 map_x, map_y (H, W) for cv2.remap into the virtual pinhole."""
    k, size = virtual_camera(model, opts)
    rot = model_rotation(model, opts)
    map_x, map_y = rectify_maps(model, k, size, rotation=rot)
    seen = np.isfinite(map_x) & np.isfinite(map_y)
    info = {"format": REMAP_FORMAT, "camera_matrix": k.tolist(), "size": list(size),
            "rotation": None if rot is None else np.asarray(rot).tolist(),
            "aligned": opts.align_to is not None, "model_type": model.type_name,
            "seen_fraction": float(seen.mean())}
    buf = io.BytesIO()
    np.savez(buf, map_x=map_x, map_y=map_y, meta=np.array(json.dumps(info)))
    return buf.getvalue(), info


def opencv_fit_npz(model: CameraModel, opts: ExportOptions) -> tuple[bytes, dict[str, Any]]:
    """NPZ with the best-fitting OpenCV model, its per-pixel residual map (H, W) and stats."""
    best = best_opencv_model(model, opts.opencv_kind)
    w, h = model.image_size
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([uu.ravel(), vv.ravel()], axis=1)
    _, d = model.unproject(pix)
    ok = np.all(np.isfinite(d), axis=1) & (d[:, 2] > 1e-3)
    resid = np.full(len(pix), np.nan)
    img, _ = cv2.projectPoints(d[ok].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), best["K"],
                               best["dist"])
    resid[ok] = np.linalg.norm(img[:, 0, :] - pix[ok], axis=1)
    r = resid[ok]
    stats = {"rms_px": float(np.sqrt(np.mean(r**2))), "median_px": float(np.median(r)),
             "p95_px": float(np.percentile(r, 95)), "max_px": float(r.max()),
             "n_pixels": int(ok.sum())}
    info = {"format": OPENCV_FIT_FORMAT, "kind": opts.opencv_kind, "image_size": [w, h],
            "source_model_type": model.type_name, "residual": stats}
    buf = io.BytesIO()
    np.savez(buf, camera_matrix=best["K"], distortion_coefficients=np.asarray(best["dist"]),
             residual_px=resid.reshape(h, w).astype(np.float32), meta=np.array(json.dumps(info)))
    return buf.getvalue(), info


def undistort_pixels(model: CameraModel, pixels: np.ndarray, opts: ExportOptions) -> np.ndarray:
    """Model pixels (N,2) -> pixels of the virtual pinhole of `opts` (the remap's camera)."""
    k, _ = virtual_camera(model, opts)
    return undistort_points(model, pixels, k, model_rotation(model, opts))


def export_bytes(model: CameraModel, fmt: str, opts: ExportOptions | None = None
                 ) -> tuple[bytes, dict[str, Any]]:
    """The file of `fmt` for `model` as bytes, and an info dict (exactness, residual)."""
    from calibration.mrcal_io import cameramodel_text

    opts = opts or ExportOptions()
    if fmt == "opencv-yaml":
        return opencv_export.opencv_yaml_text(model).encode(), {"exact": True}
    if fmt == "ros":
        text = opencv_export.ros_camera_info_yaml(model, opts.camera_name)
        return text.encode(), {"exact": True}
    if fmt == "mrcal":
        text, info = cameramodel_text(model, approximate=opts.approximate, nx=opts.spline_nx)
        return text.encode(), info
    if fmt == "remap":
        return remap_npz(model, opts)
    if fmt == "opencv-fit":
        return opencv_fit_npz(model, opts)
    raise ModelError(f"format: expected one of {', '.join(FORMATS)}, got {fmt!r}")


def export_model(model: CameraModel, fmt: str, path: str | Path,
                 opts: ExportOptions | None = None) -> dict[str, Any]:
    """Write the export of `fmt` to `path`; returns the info dict."""
    data, info = export_bytes(model, fmt, opts)
    Path(path).write_bytes(data)
    return info


def load_model_any(path: str | Path) -> CameraModel:
    """A camera model from phasecal JSON, an mrcal .cameramodel or an OpenCV FileStorage YAML.

    For comparisons (`phasecal diff`): the foreign formats give OpenCV-family models.
    """
    from calibration.mrcal_io import read_cameramodel

    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".cameramodel":
        return read_cameramodel(p)
    if suffix in (".yaml", ".yml", ".xml"):
        if not p.is_file():
            raise ModelError(f"{p}: file not found")
        k, dist, size = opencv_export.read_opencv_yaml(p)
        kind = opencv_export.opencv_yaml_model_type(p, dist.size)
        return PARAMETRIC_MODELS[kind](size, k, dist)
    return load_model(p)
