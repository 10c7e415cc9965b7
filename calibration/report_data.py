"""What a calibration report draws, recomputed from stored data only: the model, the fitted
poses (result.json) and the decoded maps of the training and held-out poses.

Nothing is taken from the fit's memory, so `phasecal report` and the REST report give the
same page for the same files, today or a year later.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.evaluate import pose_residuals, screen_jacobian, summarize
from calibration.fit.correspondences import PointSet, point_set, subsample
from calibration.models.base import CameraModel
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import ScreenGeometry
from calibration.uncertainty import model_ray_sigma, sensor_grid

# Points per pose evaluated for the report (spread evenly over the image).
REPORT_POINTS_PER_POSE = 6000


@dataclass
class PoseView:
    """Residuals of one pose: camera px, with each point's expected covariance (2x2, px^2)."""

    label: str
    heldout: bool
    pixels: np.ndarray  # (N, 2)
    residuals: np.ndarray  # (N, 2) projected - observed, camera px
    expected_cov: np.ndarray  # (N, 2, 2) decoded screen sigma pushed to camera px
    inliers: np.ndarray  # (N,) bool, as in the fit statistics
    stats: dict[str, Any]


@dataclass
class ReportData:
    """Everything the report draws."""

    model: CameraModel
    stats: dict[str, Any]
    poses: list[PoseView]
    coverage_masks: list[np.ndarray]  # (H, W) bool per pose, training then held-out
    grid: np.ndarray  # (N, 2) sensor pixels of the ray-sigma map
    grid_shape: tuple[int, int]  # (ny, nx)
    ray_sigma: np.ndarray  # (N,) rad
    ray_sigma_method: str


def _pose_view(model: CameraModel, rotation: np.ndarray, translation: np.ndarray,
               pts: PointSet, label: str, heldout: bool) -> PoseView:
    st = pose_residuals(model, _Pose(rotation, translation), pts)
    jac = screen_jacobian(model, rotation, translation, pts)
    cov = np.einsum("nij,nj,nkj->nik", jac, pts.sigma_px**2, jac)
    keys = ("rms_px", "expected_rms_px", "rms_screen_px", "expected_rms_screen_px",
            "noise_floor_ratio", "n_points", "outlier_fraction")
    return PoseView(label, heldout, pts.pixels, st["residuals"], cov, st["inliers"],
                    {k: st[k] for k in keys})


@dataclass
class _Pose:
    rotation: np.ndarray
    translation: np.ndarray


def gather(model: CameraModel, result: dict[str, Any], maps: list[DecodedMaps],
           heldout_maps: list[DecodedMaps], screen: ScreenGeometry, *,
           labels: list[str] | None = None, seed: int = 0) -> ReportData:
    """Residuals of every pose, coverage and the ray-sigma map from stored inputs.

    `result` is result.json (`stats`, `poses` with `rotation` and `translation_mm` of the
    training poses, in `maps` order); held-out poses are located by PnP with the model.
    """
    from calibration.fit.classic.pnp import estimate_pose

    fitted = result.get("poses") or []
    if fitted and len(fitted) != len(maps):
        raise ValueError(f"result.json: {len(fitted)} fitted poses but {len(maps)} training maps")
    names = labels or [f"pose {i}" for i in range(len(maps) + len(heldout_maps))]
    rng = np.random.default_rng(seed)
    views, rt, train_pts = [], [], []
    for i, m in enumerate(maps):
        pts = subsample(point_set(m, screen), REPORT_POINTS_PER_POSE)
        if fitted:
            r = np.asarray(fitted[i]["rotation"], float)
            t = np.asarray(fitted[i]["translation_mm"], float)
        else:  # no fit record: locate the pose with the model (as for held-out poses)
            r, t, _ = estimate_pose(model, pts, rng)
        views.append(_pose_view(model, r, t, pts, names[i], False))
        rt.append((r, t))
        train_pts.append(pts)
    for k, m in enumerate(heldout_maps):
        pts = subsample(point_set(m, screen), REPORT_POINTS_PER_POSE)
        r, t, _ = estimate_pose(model, pts, rng)
        views.append(_pose_view(model, r, t, pts, names[len(maps) + k], True))
    stats = dict(result.get("stats") or {})
    if "rms_px" not in stats:
        stats.update(summarize([v.stats for v in views if not v.heldout]))
    nx, ny = 48, 36
    grid = sensor_grid(model.image_size, nx, ny)
    small = [subsample(p, 800) for p in train_pts]
    sigma, method = model_ray_sigma(model, grid, rt, small, stats.get("param_std"))
    return ReportData(model, stats, views, [m.mask for m in (*maps, *heldout_maps)], grid,
                      (ny, nx), sigma, method)


def whitened(view: PoseView) -> np.ndarray:
    """(N, 2) residual components divided by their expected sigma (inliers): ~N(0, 1) if the
    model is adequate and the decoded sigmas are right."""
    r, c = view.residuals[view.inliers], view.expected_cov[view.inliers]
    sig = np.sqrt(np.stack([c[:, 0, 0], c[:, 1, 1]], axis=1))
    return r / sig


__all__ = ["PoseView", "ReportData", "gather", "whitened"]
