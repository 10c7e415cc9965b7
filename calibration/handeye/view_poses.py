"""Each view's target pose in the camera frame, with its 6x6 covariance, from a fitted camera.

The camera model is held fixed and the pose alone refitted to the view's data, weighted by
the data's own sigmas: decoded maps in the screen plane (each pixel's ray meets the screen
at its decoded point, sigma from the decoder) or observations in pixels. The covariance is
over the perturbation of `calibration.handeye.rigid` and is scaled up by chi2/dof when the
residuals are larger than the stated sigmas explain (never down).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from calibration.handeye.rigid import Rigid
from calibration.models.base import CameraModel
from calibration.shared.maps import DecodedMaps
from calibration.shared.observations import TargetObservations
from calibration.shared.plan import ScreenGeometry

# Pixels of a view's maps used for its pose (a random subset; the pose's sigma is already far
# below the robot's at a few thousand).
MAX_MAP_PIXELS = 20000
MIN_POINTS = 6


@dataclass(frozen=True)
class ViewPose:
    """Target in camera (X_cam = R X_target + t) and the covariance of its perturbation."""

    pose: Rigid
    covariance: np.ndarray  # (6, 6): rotation vector rad, translation mm
    n_points: int
    chi2_per_dof: float


def _fit(residual: Callable[[Rigid], np.ndarray], start: Rigid, n_points: int,
         sigma_known: bool) -> ViewPose:
    """Refine the pose; covariance from the whitened Jacobian at the solution."""
    sol = least_squares(lambda d: residual(start.perturbed(d)), np.zeros(6), method="lm",
                        x_scale=np.array([1e-3, 1e-3, 1e-3, 1.0, 1.0, 1.0]))
    pose = start.perturbed(sol.x)
    dof = max(sol.fun.size - 6, 1)
    chi2 = float(sol.fun @ sol.fun / dof)
    jac = sol.jac
    cov = np.linalg.inv(jac.T @ jac)
    scale = max(chi2, 1.0) if sigma_known else chi2
    return ViewPose(pose, cov * scale, n_points, chi2)


def view_pose_from_maps(model: CameraModel, maps: DecodedMaps, screen: ScreenGeometry,
                        start: Rigid, rng: np.random.Generator, *,
                        max_pixels: int = MAX_MAP_PIXELS) -> ViewPose:
    """The screen's pose from decoded maps: residuals in the screen plane, mm over sigma."""
    ok = (maps.mask & np.isfinite(maps.x) & np.isfinite(maps.y)
          & np.isfinite(maps.sigma_x) & np.isfinite(maps.sigma_y)
          & (maps.sigma_x > 0) & (maps.sigma_y > 0))
    vv, uu = np.nonzero(ok)
    if vv.size > max_pixels:
        keep = np.sort(rng.choice(vv.size, max_pixels, replace=False))
        vv, uu = vv[keep], uu[keep]
    origins, dirs = model.unproject(np.stack([uu, vv], 1).astype(np.float64))
    good = np.all(np.isfinite(origins), 1) & np.all(np.isfinite(dirs), 1)
    if good.sum() < MIN_POINTS:
        raise ValueError(f"view {maps.meta.get('pose_id') or ''}: {int(good.sum())} valid "
                         f"pixels the camera model can unproject; need >= {MIN_POINTS}")
    vv, uu, origins, dirs = vv[good], uu[good], origins[good], dirs[good]
    pitch = np.asarray(screen.pitch_mm, dtype=np.float64)
    decoded = np.stack([maps.x[vv, uu], maps.y[vv, uu]], 1) * pitch
    sigma = np.stack([maps.sigma_x[vv, uu], maps.sigma_y[vv, uu]], 1).astype(np.float64) * pitch

    def residual(pose: Rigid) -> np.ndarray:
        o = (origins - pose.translation) @ pose.rotation  # into the screen frame
        d = dirs @ pose.rotation
        lam = -o[:, 2] / d[:, 2]
        hit = o[:, :2] + lam[:, None] * d[:, :2]
        return ((hit - decoded) / sigma).ravel()

    return _fit(residual, start, int(vv.size), sigma_known=True)


def view_pose_from_observations(model: CameraModel, obs: TargetObservations,
                                start: Rigid) -> ViewPose:
    """The target's pose from observations: reprojection residuals in pixels over sigma
    (the file's sigma_px / weight; without sigma_px, the residuals set the scale)."""
    used = obs.used()
    if used.sum() < MIN_POINTS:
        raise ValueError(f"view {obs.meta.get('view') or ''}: {int(used.sum())} usable "
                         f"target points; need >= {MIN_POINTS}")
    xyz, xy = obs.target_xyz[used], obs.image_xy[used]
    sigma = (obs.sigma_px or 1.0) / obs.weights()[used]

    def residual(pose: Rigid) -> np.ndarray:
        px = model.project(xyz @ pose.rotation.T + pose.translation)
        r = (px - xy) / sigma[:, None]
        return np.where(np.isfinite(r), r, 1e3).ravel()  # a point leaving the view: large

    return _fit(residual, start, int(used.sum()), sigma_known=obs.sigma_px is not None)
