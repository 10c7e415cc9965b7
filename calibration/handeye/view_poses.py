"""The views' target poses in the camera frame with their joint covariance, from a fitted camera.

Each view's pose is refitted with the camera model fixed, weighted by the data's own sigmas:
decoded maps in the screen plane (each pixel's ray meets the screen at its decoded point,
sigma from the decoder) or observations in pixels. The covariance of all poses together
(6 per view, over the perturbation of `calibration.handeye.rigid`) then comes from the same
residuals with the model's parameters free as well, so the intrinsics' own uncertainty,
which moves every view's pose the same way (a focal length error is a depth error in all
of them), is in it, with the correlation between views. Models with more than
`MAX_MARGINAL_PARAMS` parameters (the generic ones, fitted to dense maps that pin their
rays down far better) keep the poses' covariance with the model held. The covariance is
scaled up by chi2/dof when the residuals are larger than the stated sigmas explain.
"""

from __future__ import annotations

import copy
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
MAX_MARGINAL_PARAMS = 40

Residual = Callable[[CameraModel, Rigid], np.ndarray]


@dataclass(frozen=True)
class ViewData:
    """One view's whitened residual as a function of the camera model and the target pose."""

    residual: Residual
    n_points: int
    sigma_known: bool  # False: the residuals' own scale sets the sigma


@dataclass(frozen=True)
class ViewPoses:
    """Target in camera per view (X_cam = R X_target + t) and the joint covariance of their
    perturbations, (6N, 6N) in view order."""

    poses: list[Rigid]
    covariance: np.ndarray
    chi2_per_dof: float
    intrinsics_marginalized: bool

    def block(self, i: int) -> np.ndarray:
        return self.covariance[6 * i:6 * i + 6, 6 * i:6 * i + 6]

    def subset(self, keep: list[int]) -> ViewPoses:
        idx = np.concatenate([np.arange(6 * i, 6 * i + 6) for i in keep])
        return ViewPoses([self.poses[i] for i in keep], self.covariance[np.ix_(idx, idx)],
                         self.chi2_per_dof, self.intrinsics_marginalized)


def maps_view(maps: DecodedMaps, screen: ScreenGeometry, rng: np.random.Generator, *,
              max_pixels: int = MAX_MAP_PIXELS) -> ViewData:
    """Residuals in the screen plane, mm over the decoder's sigma, of up to `max_pixels`."""
    ok = (maps.mask & np.isfinite(maps.x) & np.isfinite(maps.y)
          & np.isfinite(maps.sigma_x) & np.isfinite(maps.sigma_y)
          & (maps.sigma_x > 0) & (maps.sigma_y > 0))
    vv, uu = np.nonzero(ok)
    if vv.size > max_pixels:
        keep = np.sort(rng.choice(vv.size, max_pixels, replace=False))
        vv, uu = vv[keep], uu[keep]
    if vv.size < MIN_POINTS:
        raise ValueError(f"view {maps.meta.get('pose_id') or ''}: {vv.size} valid pixels; "
                         f"need >= {MIN_POINTS}")
    pixels = np.stack([uu, vv], 1).astype(np.float64)
    pitch = np.asarray(screen.pitch_mm, dtype=np.float64)
    decoded = np.stack([maps.x[vv, uu], maps.y[vv, uu]], 1) * pitch
    sigma = np.stack([maps.sigma_x[vv, uu], maps.sigma_y[vv, uu]], 1).astype(np.float64) * pitch

    def residual(model: CameraModel, pose: Rigid) -> np.ndarray:
        origins, dirs = model.unproject(pixels)
        o = (origins - pose.translation) @ pose.rotation  # into the screen frame
        d = dirs @ pose.rotation
        hit = o[:, :2] - (o[:, 2] / d[:, 2])[:, None] * d[:, :2]
        r = (hit - decoded) / sigma
        return np.where(np.isfinite(r), r, 0.0).ravel()  # a pixel the model cannot unproject

    return ViewData(residual, int(vv.size), sigma_known=True)


def observations_view(obs: TargetObservations) -> ViewData:
    """Reprojection residuals in pixels over sigma (the file's sigma_px / weight; without
    sigma_px, the residuals set the scale)."""
    used = obs.used()
    if used.sum() < MIN_POINTS:
        raise ValueError(f"view {obs.meta.get('view') or ''}: {int(used.sum())} usable "
                         f"target points; need >= {MIN_POINTS}")
    xyz, xy = obs.target_xyz[used], obs.image_xy[used]
    sigma = (obs.sigma_px or 1.0) / obs.weights()[used]

    def residual(model: CameraModel, pose: Rigid) -> np.ndarray:
        px = model.project(xyz @ pose.rotation.T + pose.translation)
        r = (px - xy) / sigma[:, None]
        return np.where(np.isfinite(r), r, 1e3).ravel()  # a point leaving the view: large

    return ViewData(residual, int(used.sum()), sigma_known=obs.sigma_px is not None)


def _pose_jacobian(fn: Callable[[Rigid], np.ndarray], pose: Rigid) -> np.ndarray:
    steps = np.array([1e-7] * 3 + [1e-4] * 3)
    cols = []
    for k in range(6):
        d = np.zeros(6)
        d[k] = steps[k]
        cols.append((fn(pose.perturbed(d)) - fn(pose.perturbed(-d))) / (2 * steps[k]))
    return np.stack(cols, 1)


def _params_jacobian(model: CameraModel, data: ViewData, pose: Rigid) -> np.ndarray:
    base = model.get_params()
    probe = copy.deepcopy(model)
    cols = []
    for k in range(base.size):
        h = 1e-6 * max(abs(base[k]), 1.0)
        ends = []
        for sign in (1.0, -1.0):
            p = base.copy()
            p[k] += sign * h
            probe.set_params(p)
            ends.append(data.residual(probe, pose))
        cols.append((ends[0] - ends[1]) / (2 * h))
    return np.stack(cols, 1)


def fit_view_poses(model: CameraModel, data: list[ViewData], starts: list[Rigid]) -> ViewPoses:
    """Refit each view's pose from `starts` with `model` fixed; the joint covariance."""
    poses, pose_jacs, chi2, dof = [], [], 0.0, 0
    for view, start in zip(data, starts, strict=True):
        def fn(pose: Rigid, view: ViewData = view) -> np.ndarray:
            return view.residual(model, pose)

        sol = least_squares(lambda d, fn=fn, start=start: fn(start.perturbed(d)), np.zeros(6),
                            method="lm", x_scale=np.array([1e-3] * 3 + [1.0] * 3))
        pose = start.perturbed(sol.x)
        poses.append(pose)
        pose_jacs.append(_pose_jacobian(fn, pose))
        chi2 += float(sol.fun @ sol.fun)
        dof += sol.fun.size - 6
    n = len(data)
    n_params = model.get_params().size
    marginal = n_params <= MAX_MARGINAL_PARAMS
    p = n_params if marginal else 0
    info = np.zeros((p + 6 * n, p + 6 * n))
    for i, (view, jp) in enumerate(zip(data, pose_jacs, strict=True)):
        s = slice(p + 6 * i, p + 6 * i + 6)
        info[s, s] = jp.T @ jp
        if marginal:
            jm = _params_jacobian(model, view, poses[i])
            info[:p, :p] += jm.T @ jm
            info[:p, s] = jm.T @ jp
            info[s, :p] = jp.T @ jm
    dof = max(dof - p, 1)
    chi2_per_dof = chi2 / dof
    known = all(v.sigma_known for v in data)
    scale = max(chi2_per_dof, 1.0) if known else chi2_per_dof
    cov = np.linalg.pinv(info)[p:, p:] * scale
    return ViewPoses(poses, (cov + cov.T) / 2, chi2_per_dof, marginal)
