"""Pose guidance: which screen pose to capture next to shrink the worst ray uncertainty.

From the session's own fit (a parametric model, its fitted poses and decoded points) the
information each candidate pose would add is predicted without capturing it: the image is
sampled on an even grid, each sample's ray is intersected with the candidate screen plane
and kept if it lands on the screen, and those points (with the session's median decoded
sigma, counted as the fit would count a real pose's pixels) are added to the normal
equations. The candidate whose predicted ray-sigma map has the smallest maximum over the
sensor (pixels within 70 degrees of the optical axis) wins. Candidates place the screen
centre on the ray of a pixel of a 5x5 grid over the image, at 0.5/0.7/1/1.4/2x the
session's median distance, fronto-parallel or tilted by 25, 45 or 60 degrees towards 4
azimuths; a
candidate must show the whole screen inside the image, in front of the camera and seen at
less than 70 degrees from its normal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from calibration.fit.correspondences import PointSet
from calibration.models.base import CameraModel
from calibration.shared.plan import ScreenGeometry
from calibration.uncertainty import (
    covariance,
    direction_jacobian,
    pose_information,
    ray_sigma,
    sensor_grid,
)

_FRACTIONS = (0.15, 0.33, 0.5, 0.67, 0.85)
_DISTANCE_FACTORS = (0.5, 0.7, 1.0, 1.4, 2.0)
_TILTS = ((0.0, 0.0), *((t, a) for t in (25.0, 45.0, 60.0) for a in (0.0, 90.0, 180.0, 270.0)))
_MAX_VIEW_ANGLE_DEG = 70.0
_SAMPLE_GRID = (32, 24)  # image samples per candidate
_MAP_GRID = (32, 24)  # sensor grid of the predicted ray-sigma map
_MAX_FIELD_ANGLE_DEG = 70.0  # the worst sigma is taken over pixels this close to the axis


@dataclass
class Suggestion:
    """A suggested next screen pose (X_cam = R S + t) and what it is predicted to achieve."""

    rotation: np.ndarray
    translation: np.ndarray
    distance_mm: float
    tilt_deg: float
    tilt_azimuth_deg: float
    target_px: tuple[float, float]
    image_fraction: float  # part of the image that would see the screen
    worst_before_rad: float
    worst_after_rad: float
    candidates: int
    map_before: np.ndarray  # (ny, nx) rad
    map_after: np.ndarray  # (ny, nx) rad
    outline_px: np.ndarray  # (M, 2) screen border as the camera would see it
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """JSON for the API: the pose for `screen_pose` and the human-readable placement."""
        rvec = cv2.Rodrigues(self.rotation)[0].ravel()
        return {
            "screen_pose": {"rvec": rvec.tolist(), "tvec_mm": self.translation.tolist()},
            "distance_mm": self.distance_mm, "tilt_deg": self.tilt_deg,
            "tilt_azimuth_deg": self.tilt_azimuth_deg,
            "screen_center_px": list(self.target_px), "image_fraction": self.image_fraction,
            "full_screen_visible": True,
            "predicted_worst_ray_sigma_urad": {"now": self.worst_before_rad * 1e6,
                                               "after": self.worst_after_rad * 1e6},
            "candidates_scored": self.candidates, **self.extra,
        }


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    return cv2.Rodrigues((a * angle).reshape(3, 1))[0]


def look_at(screen: ScreenGeometry, direction: np.ndarray, distance_mm: float,
            tilt_deg: float, azimuth_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) putting the screen centre `distance_mm` along `direction`, its normal tilted by
    `tilt_deg` towards `azimuth_deg` from facing the camera head-on."""
    d = direction / np.linalg.norm(direction)
    ref = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
    ex = ref - (ref @ d) * d
    ex /= np.linalg.norm(ex)
    ey = np.cross(d, ex)
    az = np.radians(azimuth_deg)
    normal = _rotation(np.cos(az) * ey - np.sin(az) * ex, np.radians(tilt_deg)) @ d
    sx = ref - (ref @ normal) * normal
    sx /= np.linalg.norm(sx)
    rot = np.stack([sx, np.cross(normal, sx), normal], axis=1)
    centre = np.array([(screen.width_px - 1) / 2 * screen.pitch_mm[0],
                       (screen.height_px - 1) / 2 * screen.pitch_mm[1], 0.0])
    return rot, distance_mm * d - rot @ centre


def _border(screen: ScreenGeometry, n: int = 9) -> np.ndarray:
    """(4n, 3) mm points along the screen's border."""
    w = (screen.width_px - 1) * screen.pitch_mm[0]
    h = (screen.height_px - 1) * screen.pitch_mm[1]
    s = np.linspace(0, 1, n)
    pts = [np.stack([s * w, 0 * s], 1), np.stack([w + 0 * s, s * h], 1),
           np.stack([(1 - s) * w, h + 0 * s], 1), np.stack([0 * s, (1 - s) * h], 1)]
    xy = np.concatenate(pts)
    return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)


def visible(model: CameraModel, screen: ScreenGeometry, rot: np.ndarray,
            t: np.ndarray) -> np.ndarray | None:
    """The screen border in pixels if the whole screen is seen (inside the image, in front,
    under 70 degrees from its normal); None otherwise."""
    cam = _border(screen) @ rot.T + t
    if np.any(cam[:, 2] <= 0):
        return None
    cosang = np.abs(cam @ rot[:, 2]) / np.linalg.norm(cam, axis=1)
    if np.any(cosang < np.cos(np.radians(_MAX_VIEW_ANGLE_DEG))):
        return None
    px = model.project(cam)
    w, h = model.image_size
    inside = (np.isfinite(px).all(axis=1) & (px[:, 0] >= 0) & (px[:, 0] <= w - 1)
              & (px[:, 1] >= 0) & (px[:, 1] <= h - 1))
    return px if inside.all() else None


def planned_points(rays: tuple[np.ndarray, np.ndarray], pixels: np.ndarray,
                   screen: ScreenGeometry, rot: np.ndarray, t: np.ndarray,
                   sigma_px: np.ndarray) -> PointSet:
    """The correspondences a pose would give at the sample pixels: ray-plane hits on the screen."""
    o, d = rays
    n = rot[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = ((t - o) @ n) / (d @ n)
        hit = (o + lam[:, None] * d - t) @ rot  # screen-frame mm
    sx, sy = hit[:, 0] / screen.pitch_mm[0], hit[:, 1] / screen.pitch_mm[1]
    on = (np.isfinite(lam) & (lam > 0) & (sx >= 0) & (sx <= screen.width_px - 1)
          & (sy >= 0) & (sy <= screen.height_px - 1))
    scr = np.stack([sx[on], sy[on]], axis=1)
    return PointSet(pixels[on], scr, np.tile(sigma_px, (len(scr), 1)), screen.pitch_mm)


def suggest_next_pose(model: CameraModel, poses: list[tuple[np.ndarray, np.ndarray]],
                      points: list[PointSet], screen: ScreenGeometry, free: np.ndarray,
                      max_points_per_pose: int = 2000) -> Suggestion:
    """The candidate pose that most lowers the worst predicted ray sigma over the sensor.

    `points` are each pose's correspondences as the fit counts them (at most
    `max_points_per_pose`); a planned pose is credited with as many.
    """
    w, h = model.image_size
    grid = sensor_grid((w, h), *_MAP_GRID)
    jd = direction_jacobian(model, grid, free)
    info0 = sum(pose_information(model, r, t, p, free) for (r, t), p in zip(poses, points,
                                                                               strict=True))
    before = ray_sigma(jd, covariance(info0))
    sigma = np.nanmedian(np.concatenate([p.sigma_px for p in points]), axis=0)
    samples = sensor_grid((w, h), *_SAMPLE_GRID)
    rays = model.unproject(samples)
    dist0 = float(np.median([np.linalg.norm(r @ np.array(
        [(screen.width_px - 1) / 2 * screen.pitch_mm[0],
         (screen.height_px - 1) / 2 * screen.pitch_mm[1], 0.0]) + t) for r, t in poses]))
    targets = np.array([[fx * (w - 1), fy * (h - 1)] for fy in _FRACTIONS for fx in _FRACTIONS])
    _, dirs = model.unproject(targets)
    cands = []
    for target, direction in zip(targets, dirs, strict=True):
        if not np.all(np.isfinite(direction)):
            continue
        for factor in _DISTANCE_FACTORS:
            for tilt, az in _TILTS:
                rot, t = look_at(screen, direction, dist0 * factor, tilt, az)
                outline = visible(model, screen, rot, t)
                if outline is None:
                    continue
                pts = planned_points(rays, samples, screen, rot, t, sigma)
                if len(pts) >= 20:
                    cands.append((rot, t, dist0 * factor, tilt, az, target, outline, pts))
    if not cands:
        raise ValueError("guidance: no candidate pose shows the whole screen; the screen may be "
                         "too large for this camera's view at the session's distances")
    region = reachable(model, grid)
    best: tuple[float, Any] | None = None
    for rot, t, dist, tilt, az, target, outline, pts in cands:
        frac = len(pts) / len(samples)
        weight = min(max_points_per_pose, frac * w * h) / len(pts)
        after = ray_sigma(jd, covariance(info0 + weight * pose_information(model, rot, t, pts,
                                                                           free)))
        score = float(np.nanmax(after[region]))
        if best is None or score < best[0]:
            best = (score, (rot, t, dist, tilt, az, target, frac, after, outline))
    assert best is not None
    rot, t, dist, tilt, az, target, frac, after, outline = best[1]
    shape = (_MAP_GRID[1], _MAP_GRID[0])
    reach = np.where(region, 1.0, np.nan)
    return Suggestion(rot, t, dist, tilt, az, (float(target[0]), float(target[1])), frac,
                      float(np.nanmax(before[region])), best[0], len(cands),
                      (before * reach).reshape(shape), (after * reach).reshape(shape), outline,
                      {"region_fraction": float(region.mean())})


def reachable(model: CameraModel, grid: np.ndarray,
              max_angle_deg: float = _MAX_FIELD_ANGLE_DEG) -> np.ndarray:
    """(N,) grid pixels whose ray is within `max_angle_deg` of the optical axis: where a whole
    screen can be seen at all (a wide-angle lens's corners near 90 degrees never see one)."""
    _, d = model.unproject(grid)
    with np.errstate(invalid="ignore"):
        return np.isfinite(d).all(axis=1) & (d[:, 2] >= np.cos(np.radians(max_angle_deg)))


def session_points(maps: list[Any], screen: ScreenGeometry,
                   max_points_per_pose: int = 1000) -> list[PointSet]:
    """Each pose's correspondences as guidance counts them (evenly subsampled)."""
    from calibration.fit.correspondences import point_set, subsample

    return [subsample(point_set(m, screen), max_points_per_pose) for m in maps]


def plan_next_pose(points: list[PointSet], image_size: tuple[int, int], screen: ScreenGeometry,
                   model_name: str = "opencv-rational",
                   max_points_per_pose: int = 1000) -> tuple[Suggestion, Any]:
    """Fit `model_name` to the session's points (>= 3 poses) and suggest the next pose.

    Returns the suggestion and the fitted model it was planned with.
    """
    from calibration.fit.classic.options import ParametricOptions
    from calibration.fit.classic.parametric import fit_parametric
    from calibration.fit.registry import PARAMETRIC
    from calibration.uncertainty import free_parameters

    if model_name not in PARAMETRIC:
        raise ValueError(f"model: guidance predicts with a parametric model "
                         f"({', '.join(PARAMETRIC)}), got {model_name!r}")
    model, poses, used, stats = fit_parametric(
        points, image_size, model_name, ParametricOptions(max_points_per_pose=max_points_per_pose))
    free = free_parameters(model, stats.get("param_std"))
    rt = [(p.rotation, p.translation) for p in poses]
    return suggest_next_pose(model, rt, used, screen, free, max_points_per_pose), model
