"""Downstream use of any model: cv2.remap maps to a virtual pinhole, undistorted points,
and the best-fitting OpenCV model with the residual it leaves per pixel."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares

from calibration.models.base import CameraModel

# Distance (mm) at which rays of a non-central model are sampled for the virtual camera.
DEFAULT_DEPTH_MM = 1000.0
_OPENCV_DIST_SIZES = {"opencv5": 5, "opencv-rational": 8}


def rectify_maps(
    model: CameraModel,
    k_virtual: np.ndarray,
    size: tuple[int, int],
    *,
    rotation: np.ndarray | None = None,
    depth_mm: float = DEFAULT_DEPTH_MM,
) -> tuple[np.ndarray, np.ndarray]:
    """float32 (map_x, map_y) of shape (H, W) for `cv2.remap` to a virtual pinhole camera.

    Virtual pixel (u, v) looks along R^T K^-1 [u, v, 1] (R: `rotation`, virtual from model
    frame); the model pixel seeing the point at `depth_mm` on that ray is where the map
    samples. NaN (cv2.remap: border) where the model does not see it.
    """
    w, h = int(size[0]), int(size[1])
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    homog = np.stack([uu.ravel(), vv.ravel(), np.ones(w * h)], axis=1)
    rays = homog @ np.linalg.inv(np.asarray(k_virtual, dtype=np.float64)).T
    if rotation is not None:
        rays = rays @ np.asarray(rotation, dtype=np.float64)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    pix = model.project(depth_mm * rays)
    return (
        pix[:, 0].reshape(h, w).astype(np.float32),
        pix[:, 1].reshape(h, w).astype(np.float32),
    )


def undistort_points(model: CameraModel, pixels: np.ndarray, k_virtual: np.ndarray,
                     rotation: np.ndarray | None = None) -> np.ndarray:
    """Model pixels (N,2) -> virtual-pinhole pixels (N,2) (cv2.undistortPoints with R and P).

    `rotation` as in `rectify_maps` (virtual from model frame); NaN where the ray does not
    point in front of the virtual camera. Non-central models: the ray directions are used.
    """
    _, d = model.unproject(np.asarray(pixels, dtype=np.float64))
    if rotation is not None:
        d = d @ np.asarray(rotation, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        xy1 = d / d[:, 2:3]
    out = xy1 @ np.asarray(k_virtual, dtype=np.float64).T
    out = out[:, :2]
    out[~(d[:, 2] > 0)] = np.nan
    return out


def best_opencv_model(
    model: CameraModel, kind: str = "opencv-rational", step_px: float = 8.0
) -> dict[str, Any]:
    """Pinhole K and distortion of `kind` closest to the model's directions, with residuals.

    Fits projected ray directions to their pixels on a grid (reprojection error in model
    pixels, robust soft-L1). Returns `K` (3x3), `dist` (OpenCV order), `pixels` (N,2),
    `residual_px` (N,) and `rms_px`.
    """
    if kind not in _OPENCV_DIST_SIZES:
        raise ValueError(f"kind: expected one of {sorted(_OPENCV_DIST_SIZES)}, got {kind!r}")
    w, h = model.image_size
    uu, vv = np.meshgrid(np.arange(0, w, step_px), np.arange(0, h, step_px))
    pix = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
    _, d = model.unproject(pix)
    ok = np.all(np.isfinite(d), axis=1) & (d[:, 2] > 1e-3)
    pix, d = pix[ok], d[ok]
    if len(pix) < 20:
        raise ValueError("best_opencv_model: fewer than 20 pixels with forward-looking rays")
    x, y = d[:, 0] / d[:, 2], d[:, 1] / d[:, 2]
    a = np.stack([x, np.ones_like(x)], axis=1)
    fx, cx = np.linalg.lstsq(a, pix[:, 0], rcond=None)[0]
    fy, cy = np.linalg.lstsq(np.stack([y, np.ones_like(y)], axis=1), pix[:, 1], rcond=None)[0]
    nd = _OPENCV_DIST_SIZES[kind]
    obj = d.reshape(-1, 1, 3)
    zero = np.zeros(3)

    def project(p: np.ndarray) -> np.ndarray:
        k = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
        img, _ = cv2.projectPoints(obj, zero, zero, k, p[4:])
        return img[:, 0, :]

    def resid(p: np.ndarray) -> np.ndarray:
        return (project(p) - pix).ravel()

    p0 = np.concatenate([[fx, fy, cx, cy], np.zeros(nd)])
    sol = least_squares(resid, p0, loss="soft_l1", f_scale=0.5, x_scale="jac")
    r = np.linalg.norm(project(sol.x) - pix, axis=1)
    k = np.array([[sol.x[0], 0, sol.x[2]], [0, sol.x[1], sol.x[3]], [0, 0, 1.0]])
    return {
        "K": k,
        "dist": sol.x[4:],
        "pixels": pix,
        "residual_px": r,
        "rms_px": float(np.sqrt(np.mean(r**2))),
    }


def _center_focal_px(model: CameraModel) -> float:
    """The focal length (px) of a pinhole with the model's pixel angle at its image center."""
    w, h = model.image_size
    c = np.array([[(w - 1) / 2, (h - 1) / 2], [(w - 1) / 2 + 1, (h - 1) / 2]])
    _, d = model.unproject(c)
    return 1.0 / float(np.arccos(np.clip(d[0] @ d[1], -1.0, 1.0)))


def stereo_rectify(model1: CameraModel, model2: CameraModel, rotation: np.ndarray,
                   translation: np.ndarray, *, size: tuple[int, int] | None = None,
                   alpha: float = 0.0) -> dict[str, Any]:
    """Rectification of a camera pair (X2 = R X1 + T): R1, R2, P1, P2, Q as cv2.stereoRectify
    gives them, and float32 cv2.remap maps (H, W) for each camera.

    Two OpenCV pinhole models (opencv5, opencv-rational) go through cv2.stereoRectify and
    cv2.initUndistortRectifyMap exactly. Any other pair (fisheye, generic): the rectifying
    rotations come from the same cv2.stereoRectify on a distortion-free virtual pinhole with
    the models' focal length at the image center, and the maps unproject each rectified
    pixel through the model (`rectify_maps`). `alpha` as in cv2.stereoRectify."""
    size = tuple(int(v) for v in (size or model1.image_size))
    rot = np.asarray(rotation, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64).reshape(3, 1)
    opencv = all(m.type_name in _OPENCV_DIST_SIZES for m in (model1, model2))
    if opencv:
        k1, d1 = model1.camera_matrix, model1.dist  # type: ignore[attr-defined]
        k2, d2 = model2.camera_matrix, model2.dist  # type: ignore[attr-defined]
    else:
        f = min(_center_focal_px(model1), _center_focal_px(model2))
        k1 = k2 = np.array([[f, 0.0, (size[0] - 1) / 2], [0.0, f, (size[1] - 1) / 2],
                            [0.0, 0.0, 1.0]])
        d1 = d2 = np.zeros(5)
    r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(k1, d1, k2, d2, size, rot, t,
                                                flags=cv2.CALIB_ZERO_DISPARITY, alpha=alpha)
    out: dict[str, Any] = {"R1": r1, "R2": r2, "P1": p1, "P2": p2, "Q": q, "image_size": size,
                           "method": "opencv" if opencv else "unprojected"}
    for i, (model, k, d, r, p) in enumerate(((model1, k1, d1, r1, p1),
                                             (model2, k2, d2, r2, p2)), start=1):
        if opencv:
            mx, my = cv2.initUndistortRectifyMap(k, d, r, p[:3, :3], size, cv2.CV_32FC1)
        else:
            mx, my = rectify_maps(model, p[:3, :3], size, rotation=r)
        out[f"map{i}_x"], out[f"map{i}_y"] = mx, my
    return out
