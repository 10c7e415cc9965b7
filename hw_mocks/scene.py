"""Screen placement and exact ray-screen intersections (which screen point each pixel sees)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import TruthCamera
from hw_mocks.panel import PanelShape

# Samples intersected per batch: small enough for the temporaries to stay in cache.
_ROW_CHUNK_SAMPLES = 1 << 16


@dataclass
class ScreenPose:
    """Screen placement in the camera frame: X_cam = R @ S + t, S = (x*pitch_x, y*pitch_y, 0) mm."""

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        """Validate and normalize the fields (errors name the field and what was expected)."""
        r = np.asarray(self.rotation, dtype=np.float64)
        t = np.asarray(self.translation, dtype=np.float64).ravel()
        if r.shape != (3, 3) or t.shape != (3,):
            raise ValueError(
                f"ScreenPose: expected rotation (3,3), translation (3,); got {r.shape}, {t.shape}"
            )
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-9) or np.linalg.det(r) < 0:
            raise ValueError("ScreenPose.rotation: not a proper rotation matrix")
        self.rotation, self.translation = r, t

    def screen_to_camera(self, screen_mm: np.ndarray) -> np.ndarray:
        """Screen-plane points (...,3) mm -> camera frame (...,3) mm."""
        return screen_mm @ self.rotation.T + self.translation

    def camera_to_screen(self, cam_mm: np.ndarray) -> np.ndarray:
        """Camera-frame points (...,3) mm -> screen frame (...,3) mm (z = 0 on the screen)."""
        return (cam_mm - self.translation) @ self.rotation

    def screen_px_to_camera(
        self, screen: ScreenGeometry, x: np.ndarray, y: np.ndarray
    ) -> np.ndarray:
        """Screen pixel coordinates -> camera-frame points (...,3) mm."""
        s = np.stack([x * screen.pitch_mm[0], y * screen.pitch_mm[1], np.zeros_like(x)], -1)
        return self.screen_to_camera(s)

    @property
    def rvec(self) -> np.ndarray:
        """Rotation as an axis-angle vector (3,) rad (OpenCV Rodrigues convention)."""
        return cv2.Rodrigues(self.rotation)[0].ravel()

    @classmethod
    def from_rvec(cls, rvec: np.ndarray, tvec_mm: np.ndarray) -> ScreenPose:
        """Pose from an OpenCV axis-angle rotation vector and a translation in mm."""
        return cls(cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0], tvec_mm)


def screen_points_at(
    camera: TruthCamera, pose: ScreenPose, screen: ScreenGeometry, u: np.ndarray, v: np.ndarray,
    panel: PanelShape | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Screen px (x, y) seen along the rays of pixel coords (u, v); NaN where the screen is missed.

    Missed means: no ray, the ray runs parallel to or away from the screen, the screen
    is seen from behind (camera on its back side), or the hit lies beyond the screen's
    extent [-0.5, W-0.5] x [-0.5, H-0.5]. `panel` (default: ideal, flat and bare) adds
    the emitting layer's shape and the cover glass (hw_mocks.panel, exact refraction).
    """
    origins, dirs = camera.rays(u, v)
    r = pose.rotation
    o_s = (origins - pose.translation) @ r  # into the screen frame
    d_s = dirs @ r
    if panel is not None and not panel.is_ideal:
        hx, hy, ok = panel.trace(screen, o_s, d_s)
        x, y = hx / screen.pitch_mm[0], hy / screen.pitch_mm[1]
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = -o_s[..., 2] / d_s[..., 2]
        hit = o_s + lam[..., None] * d_s
        x = hit[..., 0] / screen.pitch_mm[0]
        y = hit[..., 1] / screen.pitch_mm[1]
        # The screen emits towards -z of its frame (z = x cross y points into the screen).
        ok = (o_s[..., 2] < 0) & (d_s[..., 2] > 0) & (lam > 0)
    ok &= (x >= -0.5) & (x <= screen.width_px - 0.5) & (y >= -0.5) & (y <= screen.height_px - 0.5)
    return np.where(ok, x, np.nan), np.where(ok, y, np.nan)


def subpixel_offsets(supersample: int) -> np.ndarray:
    """Offsets (s,) of s equally spaced sub-sample centers inside a pixel, symmetric about 0."""
    if supersample < 1:
        raise ValueError(f"supersample: expected an integer >= 1, got {supersample}")
    return (np.arange(supersample) + 0.5) / supersample - 0.5


def screen_points(
    camera: TruthCamera, pose: ScreenPose, screen: ScreenGeometry, *, supersample: int = 1,
    panel: PanelShape | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Screen px (x, y) that each camera pixel center (or sub-sample) sees; NaN if none.

    supersample=1 gives (H, W) arrays for pixel centers. supersample=s gives (H*s, W*s)
    arrays on the sub-sample grid: sub-sample (j, i) of pixel (v, u) is at index
    [v*s + j, u*s + i] and at camera coordinates (u + off[i], v + off[j]) with
    off = `subpixel_offsets(s)`. `panel`: as in `screen_points_at`.
    """
    s = int(supersample)
    off = subpixel_offsets(s)
    w, h = camera.width, camera.height
    us = (np.arange(w)[:, None] + off[None, :]).ravel()
    vs = (np.arange(h)[:, None] + off[None, :]).ravel()
    x = np.empty((h * s, w * s))
    y = np.empty((h * s, w * s))
    rows = max(1, _ROW_CHUNK_SAMPLES // us.size)
    for r0 in range(0, vs.size, rows):
        vv, uu = np.meshgrid(vs[r0 : r0 + rows], us, indexing="ij")
        x[r0 : r0 + rows], y[r0 : r0 + rows] = screen_points_at(camera, pose, screen, uu, vv,
                                                              panel)
    return x, y
