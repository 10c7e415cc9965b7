"""Rectangles seen by a moving camera: two non-parallel boards, general motion, white flats.

Ground truth for the vanishing-point methods (rectangle and general-motion
self-calibration): a world with two
planar rectangular boards (grids of corners) whose planes are not parallel and whose
edge directions are four distinct directions, no three of them coplanar; a camera that
moves and rotates around them; and a bright quadrilateral (the screen showing a white
flat) rendered into camera images through the simulated optics and sensor.
World frame: millimetres; a camera view maps X_cam = R X_world + t.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import TruthCamera
from hw_mocks.optics import OpticalSetup
from hw_mocks.poses import fill_distance_mm, look_at_pose, rotation_about, rotation_only_poses
from hw_mocks.scene import ScreenPose
from hw_mocks.sensor import SensorModel

_MAX_TRIES = 500


@dataclass(frozen=True)
class Board:
    """A rectangle in the world: corner (0, 0) at `origin`, edges along the unit `axes` columns."""

    origin: np.ndarray  # (3,) mm
    axes: np.ndarray  # (3, 2) orthonormal edge directions x, y
    size_mm: tuple[float, float]
    grid: tuple[int, int] = (9, 7)  # corners along x, y (including the outline)

    def corners(self) -> np.ndarray:
        """(ny, nx, 3) world points of the grid corners, row j along x."""
        nx, ny = self.grid
        gx = np.linspace(0.0, self.size_mm[0], nx)
        gy = np.linspace(0.0, self.size_mm[1], ny)
        xx, yy = np.meshgrid(gx, gy)
        return self.origin + xx[..., None] * self.axes[:, 0] + yy[..., None] * self.axes[:, 1]

    def outline(self) -> np.ndarray:
        """(4, 3) world corners in order (0,0), (w,0), (w,h), (0,h)."""
        w, h = self.size_mm
        a = self.axes
        return self.origin + np.array([[0, 0], [w, 0], [w, h], [0, h]]) @ a.T


def two_board_scene(
    size_mm: tuple[float, float] = (240.0, 180.0), grid: tuple[int, int] = (9, 7),
    hinge_deg: float = 130.0, twist_deg: tuple[float, float] = (-15.0, 25.0),
) -> list[Board]:
    """Two boards on the faces of a corner of `hinge_deg` (open towards the cameras), each
    turned in its plane by `twist_deg` so that no edge runs along the hinge and no three of
    the four edge directions share a plane (the general-motion method's two non-parallel
    checkerboards)."""
    z = np.array([0, 0, 1.0])
    in_plane = np.array([[1.0, 0, 0], [0, 1.0, 0]]).T
    a_axes = rotation_about(z, np.radians(twist_deg[0])) @ in_plane
    turn = rotation_about(np.array([0, 1.0, 0]), np.radians(180.0 - hinge_deg))
    b_axes = turn @ rotation_about(z, np.radians(twist_deg[1])) @ in_plane
    w, h = size_mm
    a = Board(np.array([-w - 60.0, -h / 2, 0.0]), a_axes, size_mm, grid)
    b_origin = np.array([60.0, -h / 2, 0.0])
    return [a, Board(b_origin, b_axes, size_mm, grid)]


def vanishing_directions(boards: list[Board]) -> np.ndarray:
    """(2 * len(boards), 3) world directions of the boards' edges: x, y of each board."""
    return np.concatenate([b.axes.T for b in boards])


@dataclass(frozen=True)
class CameraView:
    """A camera placement: X_cam = rotation @ X_world + translation."""

    rotation: np.ndarray
    translation: np.ndarray

    @property
    def center(self) -> np.ndarray:
        """The camera center in the world frame."""
        return -self.rotation.T @ self.translation


def _look_at(center: np.ndarray, target: np.ndarray, roll: float) -> CameraView:
    """View from `center` towards `target` (z forward, y down), turned by `roll` rad."""
    z = target - center
    z /= np.linalg.norm(z)
    up = np.array([0, -1.0, 0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = rotation_about(z, roll) @ np.stack([x, y, z], axis=1)  # camera axes in world
    rot = r.T
    return CameraView(rot, -rot @ center)


def project_points(camera: TruthCamera, view: CameraView, world: np.ndarray) -> np.ndarray:
    """(..., 3) world points -> (..., 2) pixels; NaN where not imaged."""
    pts = world.reshape(-1, 3) @ view.rotation.T + view.translation
    return camera.project(pts).reshape(*world.shape[:-1], 2)


def _outlines_overlap(camera: TruthCamera, view: CameraView, boards: list[Board],
                      margin_px: float) -> bool:
    """Whether the images of two boards overlap or come within `margin_px` of each other."""
    polys = [project_points(camera, view, b.outline()).astype(np.float32) for b in boards]
    for i in range(len(polys)):
        for j in range(i + 1, len(polys)):
            area, _ = cv2.intersectConvexConvex(polys[i], polys[j])
            gap = min(abs(cv2.pointPolygonTest(polys[j], tuple(map(float, p)), True))
                      for p in polys[i])
            if area > 0 or gap < 2 * margin_px:
                return True
    return False


def general_motion_views(
    camera: TruthCamera, boards: list[Board], n: int, rng: np.random.Generator, *,
    distance_mm: tuple[float, float] = (450.0, 750.0), max_elevation_deg: float = 25.0,
    roll_deg: float = 20.0, aim_jitter_mm: float = 60.0, margin_px: float = 4.0,
) -> list[CameraView]:
    """`n` views from different places and orientations (general motion) that each see every
    corner of every board at least `margin_px` inside the image, the boards' images apart."""
    if n < 1:
        raise ValueError(f"n: expected >= 1 views, got {n}")
    pts = np.concatenate([b.corners().reshape(-1, 3) for b in boards])
    mid = pts.mean(axis=0)
    normals = [np.cross(b.axes[:, 0], b.axes[:, 1]) for b in boards]
    front = sum(normals) / len(normals)
    front = -front / np.linalg.norm(front)  # boards face -z: cameras sit on that side
    views: list[CameraView] = []
    for _ in range(n):
        for _ in range(_MAX_TRIES):
            az = np.radians(rng.uniform(-35.0, 35.0))
            el = np.radians(rng.uniform(-max_elevation_deg, max_elevation_deg))
            d = rng.uniform(*distance_mm)
            turn = (rotation_about(np.array([1.0, 0, 0]), el)
                    @ rotation_about(np.array([0, 1.0, 0]), az))
            dirn = turn @ front
            target = mid + rng.uniform(-aim_jitter_mm, aim_jitter_mm, 3)
            view = _look_at(mid + d * dirn, target, np.radians(rng.uniform(-roll_deg, roll_deg)))
            uv = project_points(camera, view, pts)
            inside = np.all(np.isfinite(uv)) and np.all(
                (uv >= margin_px) & (uv <= np.array([camera.width, camera.height]) - 1 - margin_px))
            if inside and not _outlines_overlap(camera, view, boards, margin_px):
                views.append(view)
                break
        else:
            raise ValueError("general_motion_views: no view sees both boards whole; "
                             "increase distance_mm or use a wider camera")
    return views


def board_pixels(
    camera: TruthCamera, boards: list[Board], views: list[CameraView], *,
    sigma_px: float = 0.0, rng: np.random.Generator | None = None,
) -> list[list[np.ndarray]]:
    """Per view, per board: (ny, nx, 2) corner pixels with Gaussian noise `sigma_px`."""
    if sigma_px > 0 and rng is None:
        raise ValueError("board_pixels: sigma_px > 0 needs an rng")
    out = []
    for view in views:
        row = []
        for b in boards:
            uv = project_points(camera, view, b.corners())
            if sigma_px > 0:
                assert rng is not None
                uv = uv + sigma_px * rng.standard_normal(uv.shape)
            row.append(uv)
        out.append(row)
    return out


def white_flat_image(
    camera: TruthCamera, pose: ScreenPose, screen: ScreenGeometry, rng: np.random.Generator, *,
    level: float = 0.8, ambient: float = 2.0e3, blur_px: float = 0.8,
    supersample: int = 2, sensor: SensorModel | None = None,
) -> np.ndarray:
    """The camera image of the screen showing a white flat: a bright quadrilateral on a dark
    room, with lens blur, vignetting, pixel-area integration, shot/read noise and
    quantization. `level` puts the brightest pixel at that fraction of the full well.

    The blur (Gaussian, `blur_px` camera px) acts in the image, as defocus does, so light
    spreads past the screen's edge; `OpticalSetup`'s screen-space blur keeps only the part
    inside the screen, which moves a white flat's edges inwards by ~0.07 px."""
    sensor = sensor or SensorModel()
    setup = OpticalSetup(camera, pose, screen, ambient=0.0, supersample=supersample)
    irr = _blurred(setup.render_irradiance(np.ones((screen.height_px, screen.width_px),
                                                   np.float32)), blur_px)
    exposure = level * sensor.full_well_e / max(float(irr.max()), 1e-9)
    return sensor.expose(irr + np.float32(ambient), exposure, 0.0, rng)


def _blurred(irradiance: np.ndarray, blur_px: float) -> np.ndarray:
    """Image-space Gaussian defocus of an irradiance image (none for blur_px = 0)."""
    if blur_px < 0:
        raise ValueError(f"blur_px: expected >= 0, got {blur_px}")
    return cv2.GaussianBlur(irradiance, (0, 0), blur_px) if blur_px > 0 else irradiance


def screen_corners_px(camera: TruthCamera, pose: ScreenPose, screen: ScreenGeometry) -> np.ndarray:
    """(4, 2) image points of the screen's outer corners (extent [-0.5, W-0.5] x [-0.5, H-0.5])."""
    w, h = screen.width_px - 0.5, screen.height_px - 0.5
    s = np.array([[-0.5, -0.5], [w, -0.5], [w, h], [-0.5, h]]) * np.asarray(screen.pitch_mm)
    return camera.project(np.c_[s, np.zeros(4)] @ pose.rotation.T + pose.translation)


def whole_screen_poses(
    camera: TruthCamera, screen: ScreenGeometry, n: int, rng: np.random.Generator, *,
    fill: tuple[float, float] = (0.45, 0.75), tilt_deg: tuple[float, float] = (25.0, 45.0),
    roll_deg: float = 20.0, margin_px: float = 8.0,
) -> list[ScreenPose]:
    """Tilted screen poses with the whole screen inside the image (quick white-flat
    intrinsics); tilt azimuths are spread evenly so that the views differ in direction."""
    dist = (fill_distance_mm(camera, screen, fill[1]), fill_distance_mm(camera, screen, fill[0]))
    size = np.array([camera.width, camera.height]) - 1 - margin_px
    az0 = rng.uniform(0, 360)
    out: list[ScreenPose] = []
    for k in range(n):
        for _ in range(_MAX_TRIES):
            u, v = rng.uniform(0.35, 0.65, 2) * (camera.width - 1, camera.height - 1)
            _, d = camera.rays(np.array([u]), np.array([v]))
            pose = look_at_pose(screen, distance_mm=rng.uniform(*dist), direction=tuple(d[0]),
                                tilt_deg=rng.uniform(*tilt_deg),
                                tilt_azimuth_deg=az0 + 360.0 * k / n + rng.uniform(-15, 15),
                                roll_deg=rng.uniform(-roll_deg, roll_deg))
            c = screen_corners_px(camera, pose, screen)
            if np.all(np.isfinite(c)) and np.all((c >= margin_px) & (c <= size)):
                out.append(pose)
                break
        else:
            raise ValueError("whole_screen_poses: no pose keeps the screen in view; lower fill")
    return out


def boards_image(
    camera: TruthCamera, boards: list[Board], view: CameraView, rng: np.random.Generator, *,
    px_per_mm: float = 1.0, level: float = 0.8, ambient: float = 2.0e3, blur_px: float = 0.8,
    supersample: int = 2, sensor: SensorModel | None = None,
) -> np.ndarray:
    """A camera image of the boards as bright (white) rectangles on a dark room, each rendered
    like a screen showing a white flat (see `white_flat_image`)."""
    sensor = sensor or SensorModel()
    irr = np.zeros((camera.height, camera.width), np.float32)
    for b in boards:
        w_px = max(round(b.size_mm[0] * px_per_mm), 2)
        h_px = max(round(b.size_mm[1] * px_per_mm), 2)
        pitch = (b.size_mm[0] / w_px, b.size_mm[1] / h_px)
        rot = view.rotation @ np.column_stack([b.axes, np.cross(b.axes[:, 0], b.axes[:, 1])])
        # screen extent starts at -0.5 px: shift so that it starts at the board's corner
        half = rot @ np.array([pitch[0], pitch[1], 0.0]) / 2
        t = view.rotation @ b.origin + view.translation + half
        setup = OpticalSetup(camera, ScreenPose(rot, t), ScreenGeometry(w_px, h_px, pitch),
                             ambient=0.0, supersample=supersample)
        irr += setup.render_irradiance(np.ones((h_px, w_px), np.float32))
    irr = _blurred(irr, blur_px)
    exposure = level * sensor.full_well_e / max(float(irr.max()), 1e-9)
    return sensor.expose(irr + np.float32(ambient), exposure, 0.0, rng)


def pan_tilt_poses(
    camera: TruthCamera, screen: ScreenGeometry, n: int, rng: np.random.Generator, *,
    fill: float = 0.5, max_rotation_deg: float = 25.0, margin_px: float = 8.0,
) -> list[ScreenPose]:
    """A fixed screen seen by a camera that only rotates about its center (a pan-tilt rig),
    the whole screen in view in every image. The first view is turned a few degrees from
    frontal: a real rig is never exactly axis-aligned, and the simulator's sub-pixel
    sampling biases perfectly axis-aligned edges by up to 1/(2 supersample) px."""
    size = np.array([camera.width, camera.height]) - 1 - margin_px
    dist = fill_distance_mm(camera, screen, fill)
    q0 = rotation_about(rng.normal(size=3), np.radians(rng.uniform(3.0, 6.0)))
    out: list[ScreenPose] = []
    for _ in range(_MAX_TRIES):
        cand = rotation_only_poses(camera, screen, 2, rng, distance_mm=dist,
                                   max_rotation_deg=max_rotation_deg, min_coverage=0.01)
        if not out:
            out.append(ScreenPose(q0 @ cand[0].rotation, q0 @ cand[0].translation))
        pose = ScreenPose(q0 @ cand[1].rotation, q0 @ cand[1].translation)
        c = screen_corners_px(camera, pose, screen)
        if np.all(np.isfinite(c)) and np.all((c >= margin_px) & (c <= size)):
            out.append(pose)
            if len(out) == n:
                return out
    raise ValueError("pan_tilt_poses: too few rotations keep the screen in view")
