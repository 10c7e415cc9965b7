"""What a calibration report draws, recomputed from stored data only: the model, the fitted
poses (result.json) and the decoded maps of the training and held-out poses.

Nothing is taken from the fit's memory, so `phasecal report` and the REST report give the
same page for the same files, today or a year later.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.evaluate import pose_residuals, screen_jacobian, summarize
from calibration.fit.classic.pnp import estimate_pose
from calibration.fit.correspondences import PointSet, point_set, subsample
from calibration.models.base import CameraModel
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import ScreenGeometry
from calibration.uncertainty import RAY_SIGMA_GRID, RAY_SIGMA_POINTS_PER_POSE, ray_sigma_map

# Points per pose evaluated for the report (spread evenly over the image).
REPORT_POINTS_PER_POSE = 6000
COVERAGE_CELLS = (16, 12)  # (nx, ny) coverage cells of models without their own mesh


@dataclass
class ReportHeader:
    """Who and what a report is about, as its first lines say it."""

    title: str
    session: str = "not given"
    rig: str = "not given"
    cameras: str = "not given"
    date: str = "not given"  # when the calibration was made
    software: str = "not given"  # the software and version that drew the report
    poses_used: list[str] = field(default_factory=list)
    heldout: list[str] = field(default_factory=list)


@dataclass
class Download:
    """A file the report offers: a label, its address, and a note (exactness, or why not)."""

    label: str
    href: str | None  # None: not available for this model (the note says why)
    note: str = ""


@dataclass
class PoseView:
    """Residuals of one pose: camera px, with each point's expected covariance (2x2, px^2)."""

    label: str
    heldout: bool
    rotation: np.ndarray  # (3, 3) screen-to-camera, fitted (training) or PnP (held-out)
    translation: np.ndarray  # (3,) mm
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
    screen: ScreenGeometry
    train_points: list[PointSet]  # each training pose's points (as evaluated for the report)


def _pose_view(model: CameraModel, rotation: np.ndarray, translation: np.ndarray,
               pts: PointSet, label: str, heldout: bool) -> PoseView:
    st = pose_residuals(model, _Pose(rotation, translation), pts)
    jac = screen_jacobian(model, rotation, translation, pts)
    cov = np.einsum("nij,nj,nkj->nik", jac, pts.sigma_px**2, jac)
    keys = ("rms_px", "expected_rms_px", "rms_screen_px", "expected_rms_screen_px",
            "noise_floor_ratio", "n_points", "outlier_fraction")
    return PoseView(label, heldout, np.asarray(rotation, float), np.asarray(translation, float),
                    pts.pixels, st["residuals"], cov, st["inliers"], {k: st[k] for k in keys})


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
    nx, ny = RAY_SIGMA_GRID
    grid, sigma, method = ray_sigma_map(model, rt, train_pts, stats.get("param_std"))
    return ReportData(model, stats, views, [m.mask for m in (*maps, *heldout_maps)], grid,
                      (ny, nx), sigma, method, screen, train_pts)


def fit_ray_sigma(model: CameraModel, result: dict[str, Any], maps: list[DecodedMaps],
                  screen: ScreenGeometry, rotation_free: bool = False
                  ) -> tuple[np.ndarray, np.ndarray, str]:
    """The ray-sigma map of a stored fit on the report's sensor grid: (grid (N, 2), sigma (N,)
    rad, how it was obtained). Only the training poses count (held-out ones add nothing).
    `rotation_free`: for comparing two fits after their best rotation."""
    fitted = result.get("poses") or []
    if fitted and len(fitted) != len(maps):
        raise ValueError(f"result.json: {len(fitted)} fitted poses but {len(maps)} training maps")
    rng = np.random.default_rng(0)
    rt, pts_all = [], []
    for i, m in enumerate(maps):
        pts = subsample(point_set(m, screen), RAY_SIGMA_POINTS_PER_POSE)
        if fitted:
            rt.append((np.asarray(fitted[i]["rotation"], float),
                       np.asarray(fitted[i]["translation_mm"], float)))
        else:
            r, t, _ = estimate_pose(model, pts, rng)
            rt.append((r, t))
        pts_all.append(pts)
    return ray_sigma_map(model, rt, pts_all, (result.get("stats") or {}).get("param_std"),
                         rotation_free)


def coverage_counts(data: ReportData) -> tuple[np.ndarray, str]:
    """Observations (pixels x training poses) per coverage cell, (ny, nx), and the cells'
    name: an sGCC model's own spline cells, else a 16 x 12 grid. The coverage plot and the
    report's words about empty cells both read this."""
    w, h = data.model.image_size
    grid = getattr(data.model, "grid", None)
    nx, ny = tuple(grid.cells) if grid is not None else COVERAGE_CELLS
    train = [m for m, v in zip(data.coverage_masks, data.poses, strict=True) if not v.heldout]
    views = np.sum(train, axis=0)
    vv, uu = np.nonzero(views > 0)
    counts = np.zeros((ny, nx))
    np.add.at(counts, (np.minimum(vv * ny // h, ny - 1), np.minimum(uu * nx // w, nx - 1)),
              views[vv, uu])
    return counts, ("spline cells" if grid is not None else "cells")


def poses_per_pixel(data: ReportData) -> np.ndarray:
    """(H, W) number of training poses that decoded each pixel."""
    return np.sum([m for m, v in zip(data.coverage_masks, data.poses, strict=True)
                   if not v.heldout], axis=0)


def whitened(view: PoseView) -> np.ndarray:
    """(N, 2) residual components divided by their expected sigma (inliers): ~N(0, 1) if the
    model is adequate and the decoded sigmas are right."""
    r, c = view.residuals[view.inliers], view.expected_cov[view.inliers]
    sig = np.sqrt(np.stack([c[:, 0, 0], c[:, 1, 1]], axis=1))
    return r / sig


__all__ = ["Download", "PoseView", "ReportData", "ReportHeader", "coverage_counts",
           "fit_ray_sigma", "gather", "poses_per_pixel", "whitened"]
