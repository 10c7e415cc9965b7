"""Where a screen can be put in front of a camera: a placement (the screen pose X_cam = R S + t)
with the screen's outline as the camera would see it and the placement in words, and the
candidate placements pose guidance chooses from.

A placement is offered only when the screen is in front of the camera and seen at less
than `MAX_VIEW_ANGLE_DEG` from its normal everywhere, with enough of it inside the image
(the whole screen for a starting pose; most of it for a next pose, which may reach past the
image's edge to put data in its corners); a placement covering less than
`MIN_IMAGE_FRACTION` of the image would add few valid pixels and is not offered either.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from calibration.fit.correspondences import PointSet
from calibration.models.base import CameraModel
from calibration.shared.plan import ScreenGeometry

MAX_VIEW_ANGLE_DEG = 70.0
MIN_IMAGE_FRACTION = 0.08  # part of the image the screen must cover
CENTRE_FRACTIONS = (0.15, 0.33, 0.5, 0.67, 0.85)  # where candidate centres appear, per axis
DISTANCE_FACTORS = (0.5, 0.7, 1.0, 1.4, 2.0)
TILTS = ((0.0, 0.0), *((t, a) for t in (25.0, 45.0, 60.0) for a in (0.0, 90.0, 180.0, 270.0)))
# The least part of a suggested next screen inside the image, unless asked otherwise. A
# phase-shifted screen is decoded pixel by pixel: each pixel that sees it is a full
# correspondence whether or not the screen's edges are in view (unlike a checkerboard,
# whose detector needs the whole grid), so a next pose may reach past the image's edge to
# put data into its corners, where the worst ray sigma is. With 60 % in view the seen part
# still spans most of the screen, so its pose (tilt included) is measured over a wide
# baseline and the operator recognizes the outline.
DEFAULT_MIN_VISIBLE = 0.6


def screen_centre_mm(screen: ScreenGeometry) -> np.ndarray:
    """(3,) the screen's centre in its own frame (mm)."""
    return np.array([(screen.width_px - 1) / 2 * screen.pitch_mm[0],
                     (screen.height_px - 1) / 2 * screen.pitch_mm[1], 0.0])


def screen_corners_mm(screen: ScreenGeometry) -> np.ndarray:
    """(4, 3) the screen's corner pixels in mm: (0, 0), (W-1, 0), (W-1, H-1), (0, H-1)."""
    w = (screen.width_px - 1) * screen.pitch_mm[0]
    h = (screen.height_px - 1) * screen.pitch_mm[1]
    return np.array([[0.0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]])


def screen_border_mm(screen: ScreenGeometry, per_side: int = 9) -> np.ndarray:
    """(4 per_side, 3) mm points along the screen's border, corner (0, 0) first."""
    c = screen_corners_mm(screen)
    s = np.linspace(0, 1, per_side, endpoint=False)[:, None]
    return np.concatenate([c[k] + s * (c[(k + 1) % 4] - c[k]) for k in range(4)])


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
    return rot, distance_mm * d - rot @ screen_centre_mm(screen)


@dataclass
class Placement:
    """A screen pose and how the camera would see it."""

    rotation: np.ndarray  # (3, 3) screen -> camera
    translation: np.ndarray  # (3,) mm
    outline_px: np.ndarray  # (4, 2) the screen's corners in camera pixels, corner (0, 0) first
    border_px: np.ndarray  # (M, 2) the screen's border in camera pixels
    image_fraction: float  # part of the image the screen covers
    centre_px: tuple[float, float]  # where the screen's centre appears
    distance_mm: float  # camera to screen centre
    sight: np.ndarray  # (3,) unit direction from the camera to the screen centre
    visible_fraction: float  # part of the screen inside the image

    def screen_pose(self) -> dict[str, list[float]]:
        """`{"rvec", "tvec_mm"}`, as `PUT /rigs/{id}/screen-pose` takes it."""
        rvec = cv2.Rodrigues(np.asarray(self.rotation, np.float64))[0].ravel()
        return {"rvec": rvec.tolist(), "tvec_mm": np.asarray(self.translation).tolist()}

    def words(self, image_size: tuple[int, int]) -> str:
        """The placement as an operator would set it up."""
        normal, sight = self.rotation[:, 2], self.sight
        # a normal (pointing away from the camera) turned towards +x brings the right edge
        # nearer: the left edge is the farther one
        turn = np.degrees(np.arctan2(normal[0], normal[2]) - np.arctan2(sight[0], sight[2]))
        nod = np.degrees(np.arctan2(normal[1], normal[2]) - np.arctan2(sight[1], sight[2]))
        parts = []
        if abs(turn) >= 5:
            parts.append(f"turned {abs(turn):.0f} deg about its vertical axis "
                         f"({'left' if turn > 0 else 'right'} edge farther)")
        if abs(nod) >= 5:
            parts.append(f"tilted {abs(nod):.0f} deg about its horizontal axis "
                         f"({'top' if nod > 0 else 'bottom'} edge farther)")
        tilt = "; ".join(parts) if parts else "facing the camera"
        return (f"{self.distance_mm:.0f} mm from the camera, {tilt}; its centre at "
                f"({self.centre_px[0]:.0f}, {self.centre_px[1]:.0f}) px, "
                f"{image_region(self.centre_px, image_size)}; it covers "
                f"{100 * self.image_fraction:.0f} % of the image"
                + ("" if self.visible_fraction >= 1 else
                   f", {100 * (1 - self.visible_fraction):.0f} % of the screen beyond its edge"))

    def to_json(self, image_size: tuple[int, int]) -> dict[str, Any]:
        """`screen_pose`, `placement` (words) and `outline_px` (4 corners, possibly outside
        the image when part of the screen is)."""
        return {"screen_pose": self.screen_pose(), "placement": self.words(image_size),
                "outline_px": np.round(self.outline_px, 2).tolist(),
                "screen_visible_fraction": round(self.visible_fraction, 3)}


def image_region(px: tuple[float, float], image_size: tuple[int, int]) -> str:
    """Where in the image a pixel lies, in words (thirds of each axis)."""
    w, h = image_size
    col = ("left", "centre", "right")[min(int(3 * px[0] / w), 2)]
    row = ("top", "middle", "bottom")[min(int(3 * px[1] / h), 2)]
    if (row, col) == ("middle", "centre"):
        return "in the middle of the image"
    return f"{row} {col} of the image" if col != "centre" else f"{row} centre of the image"


def place(model: CameraModel, screen: ScreenGeometry, rotation: np.ndarray,
          translation: np.ndarray, min_visible: float = 1.0) -> Placement | None:
    """The placement if the screen is in front of the camera, seen at less than
    `MAX_VIEW_ANGLE_DEG` from its normal everywhere, at least `min_visible` of it inside
    the image (1: the whole screen) and covering `MIN_IMAGE_FRACTION` of the image; None
    otherwise."""
    cam = screen_border_mm(screen) @ rotation.T + translation
    if np.any(cam[:, 2] <= 0):
        return None
    cosang = np.abs(cam @ rotation[:, 2]) / np.linalg.norm(cam, axis=1)
    if np.any(cosang < np.cos(np.radians(MAX_VIEW_ANGLE_DEG))):
        return None
    border = model.project(cam)
    if not _round_trip(model, cam, border):
        return None  # beyond where the model projects one-to-one
    w, h = model.image_size
    whole = bool(np.all((border >= 0) & (border <= [w - 1, h - 1])))
    visible = _visible_fraction(model, screen, rotation, translation, whole)
    if visible < min_visible - 1e-9:
        return None
    hull = cv2.convexHull(border.astype(np.float32))
    frame = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float32)
    fraction = float(cv2.intersectConvexConvex(hull, frame)[0]) / (w * h)
    if fraction < MIN_IMAGE_FRACTION:
        return None
    centre_cam = rotation @ screen_centre_mm(screen) + translation
    centre = model.project(centre_cam[None])[0]
    corners = model.project(screen_corners_mm(screen) @ rotation.T + translation)
    distance = float(np.linalg.norm(centre_cam))
    return Placement(rotation, translation, corners, border, fraction,
                     (float(centre[0]), float(centre[1])), distance, centre_cam / distance,
                     visible)


def _round_trip(model: CameraModel, cam: np.ndarray, px: np.ndarray) -> bool:
    """Whether the pixels project back onto the rays they came from (no fold of the model
    far outside its image)."""
    if not np.isfinite(px).all():
        return False
    _, d = model.unproject(px)
    ray = cam / np.linalg.norm(cam, axis=1, keepdims=True)
    with np.errstate(invalid="ignore"):
        cos = np.sum(d * ray, axis=1) / np.linalg.norm(d, axis=1)
    return bool(np.all(cos > np.cos(1e-3)))


def _visible_fraction(model: CameraModel, screen: ScreenGeometry, rotation: np.ndarray,
                      translation: np.ndarray, whole: bool, nx: int = 32, ny: int = 20
                      ) -> float:
    """Part of the screen's area inside the image: the share of the centres of an even
    grid of cells over the screen that land inside it (cell centres, not the border's
    points, which would count a sliver past the edge as a whole row of cells); 1 only when
    the `whole` border is inside, else at most one cell short of it."""
    if whole:
        return 1.0
    c = screen_corners_mm(screen)
    sx, sy = np.meshgrid((np.arange(nx) + 0.5) / nx * c[1, 0], (np.arange(ny) + 0.5) / ny * c[2, 1])
    pts = np.stack([sx.ravel(), sy.ravel(), np.zeros(sx.size)], 1) @ rotation.T + translation
    px = model.project(pts)
    w, h = model.image_size
    with np.errstate(invalid="ignore"):
        inside = ((px[:, 0] >= 0) & (px[:, 0] <= w - 1) & (px[:, 1] >= 0)
                  & (px[:, 1] <= h - 1))
    return min(float(inside.mean()), 1.0 - 1.0 / inside.size)


def candidate_placements(model: CameraModel, screen: ScreenGeometry, distance_mm: float,
                         distance_factors: tuple[float, ...] = DISTANCE_FACTORS,
                         fractions: tuple[float, ...] = CENTRE_FRACTIONS,
                         tilts: tuple[tuple[float, float], ...] = TILTS,
                         min_visible: float = 1.0) -> list[tuple[Placement, float, float]]:
    """(placement, tilt deg, tilt azimuth deg) of every candidate that `place` accepts: the
    screen centre on the ray of a pixel of an even grid (`fractions` of the image per axis),
    at `distance_factors` times `distance_mm`, facing the camera or tilted by `tilts`, with
at least `min_visible` of the screen inside the image."""
    w, h = model.image_size
    targets = np.array([[fx * (w - 1), fy * (h - 1)] for fy in fractions for fx in fractions])
    _, dirs = model.unproject(targets)
    out = []
    for direction in dirs:
        if not np.all(np.isfinite(direction)):
            continue
        for factor in distance_factors:
            for tilt, az in tilts:
                rot, t = look_at(screen, direction, distance_mm * factor, tilt, az)
                found = place(model, screen, rot, t, min_visible)
                if found is not None:
                    out.append((found, tilt, az))
    return out


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


def outline_distance(a: np.ndarray, b: np.ndarray, image_size: tuple[int, int]) -> float:
    """Mean distance between corresponding corners of two (4, 2) outlines, as a fraction of
    the image diagonal: near 0 for the same placement seen twice."""
    return float(np.mean(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=1))
                 / np.hypot(*image_size))
