"""Ground truth for several cameras on one rig: known cameras at known relative poses, screen
views that chosen groups of them see together, and the decoded maps or sparse target points
each camera would record. For tests and benchmarks that check the rig fit from outside."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.shared.maps import DecodedMaps
from calibration.shared.observations import TargetObservations
from calibration.shared.plan import ScreenGeometry
from hw_mocks.camera_base import TruthCamera
from hw_mocks.poses import coverage, look_at_pose, rotation_about
from hw_mocks.scene import ScreenPose
from hw_mocks.synthetic import synthetic_maps

_MAX_TRIES_PER_VIEW = 400


@dataclass
class RigTruth:
    """Cameras with their reference-to-camera transforms (X_cam = R X_ref + t, mm)."""

    cameras: dict[str, TruthCamera]
    rotations: dict[str, np.ndarray]
    translations: dict[str, np.ndarray]

    def screen_pose(self, camera: str, view: ScreenPose) -> ScreenPose:
        """A screen pose given in the reference frame, as seen from `camera`."""
        r, t = self.rotations[camera], self.translations[camera]
        return ScreenPose(r @ view.rotation, r @ view.translation + t)

    def relative(self, first: str, second: str) -> tuple[np.ndarray, np.ndarray]:
        """(R, T) with X_second = R X_first + T."""
        r = self.rotations[second] @ self.rotations[first].T
        return r, self.translations[second] - r @ self.translations[first]


def camera_at(position_mm: tuple[float, float, float], yaw_deg: float = 0.0,
              pitch_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Reference-to-camera (R, t) of a camera centred at `position_mm` (reference frame),
    turned by `yaw_deg` about the reference y axis and `pitch_deg` about its x axis."""
    r_cam_to_ref = (rotation_about(np.array([0.0, 1.0, 0.0]), np.radians(yaw_deg))
                    @ rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(pitch_deg)))
    r = r_cam_to_ref.T
    return r, -r @ np.asarray(position_mm, dtype=np.float64)


def shared_views(truth: RigTruth, screen: ScreenGeometry, groups: list[tuple[str, ...]],
                 per_group: int, rng: np.random.Generator, *,
                 distance_mm: tuple[float, float] = (350.0, 550.0),
                 tilt_deg: tuple[float, float] = (10.0, 35.0),
                 min_coverage: float = 0.3) -> list[tuple[tuple[str, ...], ScreenPose]]:
    """`per_group` screen poses (reference frame) for each group of cameras, each seen by every
    camera of its group over at least `min_coverage` of its image; tilts spread over azimuths."""
    views = []
    for group in groups:
        center = np.mean([-truth.rotations[c].T @ truth.translations[c] for c in group], axis=0)
        axis = np.mean([truth.rotations[c][2] for c in group], axis=0)  # mean optical axis
        axis /= np.linalg.norm(axis)
        az0 = rng.uniform(0, 360)
        for k in range(per_group):
            for _ in range(_MAX_TRIES_PER_VIEW):
                d = axis + 0.12 * rng.standard_normal(3)
                d /= np.linalg.norm(d)
                local = look_at_pose(screen, distance_mm=rng.uniform(*distance_mm),
                                     direction=tuple(d), tilt_deg=rng.uniform(*tilt_deg),
                                     tilt_azimuth_deg=az0 + 360.0 * k / per_group
                                     + rng.uniform(-25, 25),
                                     roll_deg=rng.uniform(-15, 15))
                view = ScreenPose(local.rotation, local.translation + center)
                if all(coverage(truth.cameras[c], truth.screen_pose(c, view), screen)
                       >= min_coverage for c in group):
                    views.append((group, view))
                    break
            else:
                raise ValueError(f"shared_views: no view seen by all of {group} found; "
                                 "bring the cameras closer or lower min_coverage")
    return views


def view_maps(truth: RigTruth, camera: str, view: ScreenPose, screen: ScreenGeometry, *,
              sigma_px: float, rng: np.random.Generator, view_id: str = "") -> DecodedMaps:
    """Decoded maps camera `camera` records of the screen at `view` (screen sigma_px noise)."""
    maps, _ = synthetic_maps(truth.cameras[camera], truth.screen_pose(camera, view), screen,
                             sigma_px=sigma_px, rng=rng, pose_id=view_id)
    return maps


def grid_points(screen: ScreenGeometry, cols: int = 9, rows: int = 6) -> np.ndarray:
    """(cols*rows, 3) corner points of a chessboard drawn over the middle 80% of the screen,
    mm in the screen frame."""
    xs = np.linspace(0.1, 0.9, cols) * (screen.width_px - 1) * screen.pitch_mm[0]
    ys = np.linspace(0.1, 0.9, rows) * (screen.height_px - 1) * screen.pitch_mm[1]
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])


def view_observations(truth: RigTruth, camera: str, view: ScreenPose, points: np.ndarray, *,
                      sigma_px: float, rng: np.random.Generator, view_id: str = "",
                      state_sigma: bool = True) -> TargetObservations:
    """Target points seen by `camera` at `view` with Gaussian pixel noise `sigma_px` (NaN rows
    where not imaged); the file states the sigma unless `state_sigma` is False."""
    cam = truth.cameras[camera]
    pose = truth.screen_pose(camera, view)
    uv = cam.project(pose.screen_to_camera(points))
    uv = uv + sigma_px * rng.standard_normal(uv.shape)
    uv[~cam.in_image(uv)] = np.nan
    return TargetObservations(image_xy=uv, target_xyz=points.copy(),
                              image_size=(cam.width, cam.height),
                              sigma_px=sigma_px if state_sigma else None,
                              meta={"camera": camera, "view": view_id,
                                    "source": "hw_mocks.rig_truth"})
