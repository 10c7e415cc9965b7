"""Pose of the screen for a known (any central) model: RANSAC homography on rays, then PnP."""

from __future__ import annotations

import cv2
import numpy as np

from calibration.fit.classic.homography import ransac_homography
from calibration.fit.classic.zhang import pose_from_homography
from calibration.fit.correspondences import PointSet
from calibration.fit.ransac import DegenerateError
from calibration.models.base import CameraModel

# Rays within this angle of the optical axis are used (x/z stays well conditioned).
_MAX_OFF_AXIS_DEG = 80.0


def pixel_angle(model: CameraModel) -> float:
    """Angle (rad) between the rays of two adjacent pixels at the image center."""
    w, h = model.image_size
    c = np.array([[(w - 1) / 2, (h - 1) / 2], [(w - 1) / 2 + 1, (h - 1) / 2]])
    _, d = model.unproject(c)
    return float(np.arccos(np.clip(d[0] @ d[1], -1.0, 1.0)))


def estimate_pose(
    model: CameraModel, points: PointSet, rng: np.random.Generator, *, threshold_px: float = 3.0,
    iterations: int = 300,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, t, inlier mask) of a screen pose from decoded points, robust to gross outliers.

    The pixels are unprojected with the model, so any central model works; inliers are
    points whose normalized ray error is below `threshold_px` pixel angles.
    """
    if not model.is_central:
        raise ValueError(f"estimate_pose: model {model.type_name!r} is not central")
    _, d = model.unproject(points.pixels)
    ok = np.all(np.isfinite(d), axis=1) & (d[:, 2] > np.cos(np.radians(_MAX_OFF_AXIS_DEG)))
    if ok.sum() < 8:
        raise DegenerateError(f"pose: only {int(ok.sum())} usable points (need >= 8)")
    norm = d[ok, :2] / d[ok, 2:]
    # Centered screen coordinates: the plane's origin is then in front of the camera, which
    # fixes the sign of the homography decomposition even for wide-angle views.
    center = points.screen_mm[ok].mean(axis=0)
    obj = points.screen_mm[ok] - center
    thr = threshold_px * pixel_angle(model)
    h, inl = ransac_homography(obj[:, :2], norm, thr, rng, iterations=iterations)
    r, t = pose_from_homography(np.eye(3), h)
    rvec, _ = cv2.Rodrigues(r)
    _, rvec, tvec = cv2.solvePnP(obj[inl], norm[inl], np.eye(3), None, rvec, t.reshape(3, 1),
                                 useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    r, _ = cv2.Rodrigues(rvec)
    t = tvec.ravel() - r @ center
    inliers = np.zeros(len(points), dtype=bool)
    inliers[np.flatnonzero(ok)[inl]] = True
    return r, t, inliers
