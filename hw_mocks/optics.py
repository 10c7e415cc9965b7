"""Image formation: what the camera's pixels receive from the light the screen emits."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from calibration.plan import ScreenGeometry
from hw_mocks.cameras import TruthCamera
from hw_mocks.scene import ScreenPose, screen_points, screen_points_at, subpixel_offsets


@dataclass
class _Sampler:
    """Precomputed bilinear taps of every sub-sample into the padded, flattened screen image."""

    index: np.ndarray  # int32/int64 (H*s, W*s): flat index of the top-left tap
    fx: np.ndarray  # float32 (H*s, W*s): fractional x weight
    fy: np.ndarray  # float32 (H*s, W*s): fractional y weight
    padded_width: int
    zero_start: int  # flat index where a block of zeros begins (for samples off the screen)


def _build_sampler(x: np.ndarray, y: np.ndarray, screen: ScreenGeometry) -> _Sampler:
    """Bilinear taps at exact float64 positions (cv2.remap would quantize them to 1/32 px)."""
    wp, hp = screen.width_px + 2, screen.height_px + 2
    ok = np.isfinite(x) & np.isfinite(y)
    xp = np.where(ok, x, 0.0) + 1.0  # padded coordinates, in [0.5, W + 0.5]
    yp = np.where(ok, y, 0.0) + 1.0
    x0 = np.clip(np.floor(xp), 0, wp - 2)
    y0 = np.clip(np.floor(yp), 0, hp - 2)
    zero_start = wp * hp
    dtype = np.int32 if zero_start + wp + 2 < np.iinfo(np.int32).max else np.int64
    index = np.where(ok, y0 * wp + x0, zero_start).astype(dtype)
    fx = np.where(ok, xp - x0, 0.0).astype(np.float32)
    fy = np.where(ok, yp - y0, 0.0).astype(np.float32)
    return _Sampler(index, fx, fy, wp, zero_start)


def vignetting_map(camera: TruthCamera, falloff: float) -> np.ndarray:
    """Relative illumination (H,W): 1 at the image center, 1 - falloff at the corners (r^2)."""
    if not 0.0 <= falloff < 1.0:
        raise ValueError(f"vignetting: expected a falloff in [0, 1), got {falloff}")
    u, v = camera.pixel_grid()
    du = u - (camera.width - 1) / 2
    dv = v - (camera.height - 1) / 2
    rho2 = (du**2 + dv**2) / (((camera.width - 1) / 2) ** 2 + ((camera.height - 1) / 2) ** 2)
    return 1.0 - falloff * rho2


@dataclass
class OpticalSetup:
    """A camera looking at a screen: blur, pixel-area integration, vignetting, stray light."""

    camera: TruthCamera
    pose: ScreenPose
    screen: ScreenGeometry
    blur_sigma_screen_px: float = 0.0  # defocus as a Gaussian width on the screen (screen px)
    vignetting: float = 0.3  # relative falloff at the image corner
    irradiance_scale: float = 2.0e5  # electrons/s per pixel for linear light 1.0 at the center
    ambient: float = 0.0  # constant stray light, electrons/s per pixel
    supersample: int = 2  # s x s sub-samples per pixel (pixel-area integration)
    _sampler: _Sampler | None = field(default=None, init=False, repr=False)
    _gain: np.ndarray | None = field(default=None, init=False, repr=False)
    _visible: np.ndarray | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.blur_sigma_screen_px < 0:
            raise ValueError(
                f"blur_sigma_screen_px: expected >= 0, got {self.blur_sigma_screen_px}"
            )
        if self.irradiance_scale <= 0 or self.ambient < 0:
            raise ValueError("irradiance_scale must be > 0 and ambient >= 0 (electrons/s)")
        subpixel_offsets(self.supersample)  # validates supersample
        vignetting_map(self.camera, self.vignetting)  # validates vignetting

    def _prepare(self) -> _Sampler:
        """Compute and cache the sub-sample screen points, taps and per-pixel gain."""
        if self._sampler is None:
            s = self.supersample
            x, y = screen_points(self.camera, self.pose, self.screen, supersample=s)
            self._sampler = _build_sampler(x, y, self.screen)
            h, w = self.camera.height, self.camera.width
            hits = np.isfinite(x).reshape(h, s, w, s)
            self._visible = hits.all(axis=(1, 3))
            self._gain = (
                self.irradiance_scale * vignetting_map(self.camera, self.vignetting)
            ).astype(np.float32)
        return self._sampler

    def blurred(self, display_linear: np.ndarray) -> np.ndarray:
        """The screen image after the optical blur (Gaussian of blur_sigma_screen_px), float32."""
        img = np.asarray(display_linear, dtype=np.float32)
        expected = (self.screen.height_px, self.screen.width_px)
        if img.shape != expected:
            raise ValueError(
                f"display image: expected shape {expected} (screen height, width), got {img.shape}"
            )
        if self.blur_sigma_screen_px > 0:
            sig = self.blur_sigma_screen_px
            k = 2 * int(np.ceil(4 * sig)) + 1
            # Beyond the screen's edge is the dark bezel: blur mixes it in.
            img = cv2.GaussianBlur(img, (k, k), sig, sigmaY=sig, borderType=cv2.BORDER_CONSTANT)
        return img

    def render_irradiance(self, display_linear: np.ndarray) -> np.ndarray:
        """Display linear light (H_s, W_s) in [0, 1] -> (H, W) float32 electrons/s at the sensor."""
        smp = self._prepare()
        img = self.blurred(display_linear)
        padded = cv2.copyMakeBorder(img, 1, 1, 1, 1, cv2.BORDER_REPLICATE)
        flat = np.concatenate([padded.ravel(), np.zeros(smp.padded_width + 2, np.float32)])
        i = smp.index
        top = flat[i] + smp.fx * (flat[i + 1] - flat[i])
        bottom = flat[i + smp.padded_width] + smp.fx * (
            flat[i + smp.padded_width + 1] - flat[i + smp.padded_width]
        )
        fine = top + smp.fy * (bottom - top)
        s = self.supersample
        h, w = self.camera.height, self.camera.width
        mean = fine.reshape(h, s, w, s).mean(axis=(1, 3), dtype=np.float32)
        assert self._gain is not None
        return mean * self._gain + np.float32(self.ambient)

    def truth(self) -> dict[str, Any]:
        """Ground truth of this setup (screen points, visibility, blur, vignetting).

        x_true/y_true are the screen px seen by the pixel centers (float64, NaN if none);
        visible: all sub-samples of the pixel see the screen; edge_distance_px: distance of
        the seen point from the screen's border (pixels within a few blur widths of it mix
        in the dark bezel); blur_x/y: optical blur combined with the pixel footprint
        (sub-sample spread) as one Gaussian-equivalent width in screen px; the bilinear
        sampling of the screen's pixels adds a bias below 0.004 screen px for periods of
        16 px and more (smaller for longer periods).
        """
        self._prepare()
        u, v = self.camera.pixel_grid()
        x, y = screen_points_at(self.camera, self.pose, self.screen, u, v)
        # Footprint of a pixel on the screen: Jacobian of (x, y) over (u, v).
        jxu, jxv = np.gradient(x, axis=1), np.gradient(x, axis=0)
        jyu, jyv = np.gradient(y, axis=1), np.gradient(y, axis=0)
        s = self.supersample
        box_var = (s * s - 1) / (12.0 * s * s)  # variance of s equally spaced sub-samples
        foot_x = np.sqrt(box_var * (jxu**2 + jxv**2))
        foot_y = np.sqrt(box_var * (jyu**2 + jyv**2))
        blur2 = self.blur_sigma_screen_px**2
        w_s, h_s = self.screen.width_px, self.screen.height_px
        edge = np.minimum(np.minimum(x + 0.5, w_s - 0.5 - x), np.minimum(y + 0.5, h_s - 0.5 - y))
        assert self._visible is not None and self._gain is not None
        return {
            "x_true": x,
            "y_true": y,
            "visible": self._visible.copy(),
            "visible_center": np.isfinite(x),
            "blur_sigma_screen_px": self.blur_sigma_screen_px,
            "footprint_sigma_x": foot_x,
            "footprint_sigma_y": foot_y,
            "blur_x": np.sqrt(blur2 + foot_x**2),
            "blur_y": np.sqrt(blur2 + foot_y**2),
            "edge_distance_px": edge,
            "vignetting": vignetting_map(self.camera, self.vignetting),
            "irradiance_gain": self._gain.copy(),
            "pose": self.pose,
        }
