"""Screen poses for simulations: look-at placement, varied calibration poses, pure rotations."""

from __future__ import annotations

import numpy as np

from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import TruthCamera
from hw_mocks.scene import ScreenPose, screen_points_at

# Coarse grid (columns, rows) on which the covered image fraction of a pose is measured.
_COVERAGE_GRID = (32, 24)
_MAX_TRIES_PER_POSE = 200


def _screen_center_mm(screen: ScreenGeometry) -> np.ndarray:
    """The screen's center point in screen-frame millimetres."""
    return np.array(
        [
            (screen.width_px - 1) / 2 * screen.pitch_mm[0],
            (screen.height_px - 1) / 2 * screen.pitch_mm[1],
            0,
        ]
    )


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix about `axis` (any length, normalised here) by `angle` radians, right
    handed (Rodrigues formula): how the simulator tilts, rolls and turns screens and cameras."""
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def _screen_axes(normal: np.ndarray, roll_rad: float) -> np.ndarray:
    """Rotation whose columns are the screen x, y, z axes in the camera frame.

    z is `normal` (pointing away from the camera); x follows the camera's x axis as
    closely as possible, then turns by `roll_rad` about z.
    """
    n = normal / np.linalg.norm(normal)
    ref = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    ex = ref - (ref @ n) * n
    ex /= np.linalg.norm(ex)
    ex = rotation_about(n, roll_rad) @ ex
    ey = np.cross(n, ex)
    return np.stack([ex, ey, n], axis=1)


def look_at_pose(
    screen: ScreenGeometry,
    *,
    distance_mm: float,
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0),
    target_px: tuple[float, float] | None = None,
    tilt_deg: float = 0.0,
    tilt_azimuth_deg: float = 0.0,
    roll_deg: float = 0.0,
) -> ScreenPose:
    """The screen point `target_px` (default: center) placed `distance_mm` along `direction`.

    `direction` is a camera-frame viewing direction (e.g. a pixel's ray). The screen
    normal is that direction tilted by `tilt_deg` towards azimuth `tilt_azimuth_deg`
    (measured in the plane perpendicular to it); `roll_deg` turns the screen in its plane.
    """
    if distance_mm <= 0:
        raise ValueError(f"distance_mm: expected > 0, got {distance_mm}")
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    base = _screen_axes(d, 0.0)
    az = np.radians(tilt_azimuth_deg)
    tilt_axis = np.cos(az) * base[:, 1] - np.sin(az) * base[:, 0]
    normal = rotation_about(tilt_axis, np.radians(tilt_deg)) @ d
    rot = _screen_axes(normal, np.radians(roll_deg))
    if target_px is None:
        s_target = _screen_center_mm(screen)
    else:
        s_target = np.array(
            [target_px[0] * screen.pitch_mm[0], target_px[1] * screen.pitch_mm[1], 0.0]
        )
    t = distance_mm * d - rot @ s_target
    return ScreenPose(rot, t)


def coverage(camera: TruthCamera, pose: ScreenPose, screen: ScreenGeometry) -> float:
    """Fraction of the image (sampled on a coarse grid) that sees the screen."""
    gu, gv = _COVERAGE_GRID
    u = (np.arange(gu) + 0.5) * camera.width / gu - 0.5
    v = (np.arange(gv) + 0.5) * camera.height / gv - 0.5
    uu, vv = np.meshgrid(u, v)
    x, _ = screen_points_at(camera, pose, screen, uu, vv)
    return float(np.mean(np.isfinite(x)))


def _horizontal_fov_rad(camera: TruthCamera) -> float:
    """Angle between the rays through the left and right image edge centers (the widest seen)."""
    mid = (camera.height - 1) / 2
    u = np.linspace(-0.5, camera.width - 0.5, 65)
    _, d = camera.rays(u, np.full_like(u, mid))
    d = d[np.isfinite(d[:, 0])]
    return float(np.arccos(np.clip(d[0] @ d[-1], -1.0, 1.0)))


def fill_distance_mm(camera: TruthCamera, screen: ScreenGeometry, fill: float) -> float:
    """Distance at which the screen width spans `fill` times the camera's horizontal FOV."""
    half = min(fill * _horizontal_fov_rad(camera) / 2, np.radians(80.0))
    return screen.width_px * screen.pitch_mm[0] / 2 / np.tan(half)


def random_poses(
    camera: TruthCamera,
    screen: ScreenGeometry,
    n: int,
    rng: np.random.Generator,
    *,
    distance_mm: float | tuple[float, float] | None = None,
    tilt_deg: tuple[float, float] = (10.0, 40.0),
    roll_deg: float = 20.0,
    min_coverage: float = 0.3,
) -> list[ScreenPose]:
    """Varied, well-conditioned calibration poses in which the screen covers much of the image.

    Each pose puts the screen center on the ray of a random pixel in the central 60% of
    the image, tilted by a random angle in `tilt_deg` (azimuths spread evenly over the
    poses so that the tilts differ in direction), rolled by up to +-`roll_deg`, at a
    distance drawn from `distance_mm` (default: where the screen spans 0.8-1.3 of the
    FOV). A candidate is kept only if at least `min_coverage` of the image sees the screen.
    """
    if n < 1:
        raise ValueError(f"n: expected >= 1 poses, got {n}")
    if distance_mm is None:
        dist_range = (fill_distance_mm(camera, screen, 1.3), fill_distance_mm(camera, screen, 0.8))
    elif isinstance(distance_mm, tuple):
        dist_range = (float(distance_mm[0]), float(distance_mm[1]))
    else:
        dist_range = (float(distance_mm), float(distance_mm))
    azimuth0 = rng.uniform(0, 360)
    poses: list[ScreenPose] = []
    for k in range(n):
        for _ in range(_MAX_TRIES_PER_POSE):
            u = rng.uniform(0.2, 0.8) * (camera.width - 1)
            v = rng.uniform(0.2, 0.8) * (camera.height - 1)
            _, d = camera.rays(np.array([u]), np.array([v]))
            if not np.all(np.isfinite(d)):
                continue
            pose = look_at_pose(
                screen,
                distance_mm=rng.uniform(*dist_range),
                direction=tuple(d[0]),
                tilt_deg=rng.uniform(*tilt_deg),
                tilt_azimuth_deg=azimuth0 + 360.0 * k / n + rng.uniform(-20, 20),
                roll_deg=rng.uniform(-roll_deg, roll_deg),
            )
            if coverage(camera, pose, screen) >= min_coverage:
                poses.append(pose)
                break
        else:
            raise ValueError(
                f"random_poses: no pose with coverage >= {min_coverage} found for pose {k} "
                f"(distance {dist_range} mm, tilt {tilt_deg} deg); lower min_coverage or "
                "move the screen closer"
            )
    return poses


def rotation_only_poses(
    camera: TruthCamera,
    screen: ScreenGeometry,
    n: int,
    rng: np.random.Generator,
    *,
    distance_mm: float | None = None,
    max_rotation_deg: float = 15.0,
    min_coverage: float = 0.3,
) -> list[ScreenPose]:
    """Poses of a fixed screen seen by a camera that only rotates about its center.

    The first pose is a frontal placement (the base); pose k is R_k = Q_k R_0,
    t_k = Q_k t_0 with a random camera rotation Q_k of up to `max_rotation_deg`, so
    Q_k = R_k R_0^T. Each pose keeps at least `min_coverage` of the image on the screen.
    """
    if n < 2:
        raise ValueError(f"n: expected >= 2 poses for rotation-only data, got {n}")
    dist = fill_distance_mm(camera, screen, 0.9) if distance_mm is None else float(distance_mm)
    base = look_at_pose(screen, distance_mm=dist)
    poses = [base]
    while len(poses) < n:
        for _ in range(_MAX_TRIES_PER_POSE):
            axis = rng.normal(size=3)
            angle = np.radians(rng.uniform(0.3, 1.0) * max_rotation_deg)
            q = rotation_about(axis, angle)
            pose = ScreenPose(q @ base.rotation, q @ base.translation)
            if coverage(camera, pose, screen) >= min_coverage:
                poses.append(pose)
                break
        else:
            raise ValueError(
                f"rotation_only_poses: no rotation of up to {max_rotation_deg} deg keeps "
                f"coverage >= {min_coverage}; lower max_rotation_deg"
            )
    return poses


# (distance mm, tilt deg, tilt azimuth deg): the setup of Pak's smooth generic calibration, 3
# poses that each see
# "1024 x 1024 data points", i.e. fill the whole image of a ~60 deg camera (`mild_pinhole`,
# `smooth_noncentral`) on the default 1920x1080, 0.2745 mm screen, at a 2.7x depth spread.
FULL_VIEW_DESIGN = ((60.0, 30.0, 0.0), (110.0, 30.0, 120.0), (160.0, 20.0, 240.0))


def full_view_poses(screen: ScreenGeometry) -> list[ScreenPose]:
    """Three tilted screen poses at different depths, each covering the whole image.

    Every pixel is seen three times at three depths, which is what pins down a non-central
    camera's ray origins; random poses that each cover part of the image leave edge pixels
    seen once or twice and the fit's error there several times larger (benchmarks/sgcc.py).
    """
    return [
        look_at_pose(screen, distance_mm=d, tilt_deg=t, tilt_azimuth_deg=a)
        for d, t, a in FULL_VIEW_DESIGN
    ]
