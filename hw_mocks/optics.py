"""Image formation: what the camera's pixels receive from the light the screen emits."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import TruthCamera
from hw_mocks.optics_sampling import ScreenSampler
from hw_mocks.panel import PanelShape
from hw_mocks.scene import ScreenPose, screen_points, subpixel_offsets


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
    """A camera looking at a screen: blur, pixel-area integration, vignetting, stray light.

    Ray casting is done once and cached; assigning a field resets the cache (replace a
    pose rather than editing its arrays in place).
    """

    camera: TruthCamera
    pose: ScreenPose
    screen: ScreenGeometry
    blur_sigma_screen_px: float = 0.0  # defocus as a Gaussian width on the screen (screen px)
    vignetting: float = 0.3  # relative falloff at the image corner
    irradiance_scale: float = 2.0e5  # electrons/s per pixel for linear light 1.0 at the center
    ambient: float = 0.0  # constant stray light, electrons/s per pixel
    supersample: int = 2  # s x s sub-samples per pixel (pixel-area integration)
    panel: PanelShape | None = None  # shaped panel behind cover glass (None: ideal screen)
    _sampler: ScreenSampler | None = field(default=None, init=False, repr=False)
    _gain: np.ndarray | None = field(default=None, init=False, repr=False)
    _visible: np.ndarray | None = field(default=None, init=False, repr=False)
    _truth: dict[str, Any] | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        """Validate and normalize the fields (errors name the field and what was expected)."""
        if self.blur_sigma_screen_px < 0:
            raise ValueError(
                f"blur_sigma_screen_px: expected >= 0, got {self.blur_sigma_screen_px}"
            )
        if self.irradiance_scale <= 0 or self.ambient < 0:
            raise ValueError("irradiance_scale must be > 0 and ambient >= 0 (electrons/s)")
        subpixel_offsets(self.supersample)  # validates supersample
        vignetting_map(self.camera, self.vignetting)  # validates vignetting

    def __setattr__(self, name: str, value: Any) -> None:
        """Set a field; changing a public one (blur, pose, ...) drops the cached rendering state."""
        super().__setattr__(name, value)
        if not name.startswith("_") and getattr(self, "_sampler", None) is not None:
            self._sampler = self._gain = self._visible = self._truth = None

    def _prepare(self) -> ScreenSampler:
        """Compute and cache the sub-sample screen points, the sampler and per-pixel gain."""
        if self._sampler is None:
            s = self.supersample
            x, y = screen_points(self.camera, self.pose, self.screen, supersample=s,
                                 panel=self.panel)
            self._sampler = ScreenSampler(x, y, self.screen, s, self.blur_sigma_screen_px)
            h, w = self.camera.height, self.camera.width
            self._visible = np.isfinite(x).reshape(h, s, w, s).all(axis=(1, 3))
            self._gain = (
                self.irradiance_scale * vignetting_map(self.camera, self.vignetting)
            ).astype(np.float32)
        return self._sampler

    def blurred(self, display_linear: np.ndarray) -> np.ndarray:
        """The screen image after the optical blur (Gaussian of blur_sigma_screen_px), float32."""
        return self._prepare().blurred(display_linear)

    def render_irradiance(self, display_linear: np.ndarray) -> np.ndarray:
        """Display linear light (H_s, W_s) in [0, 1] -> (H, W) float32 electrons/s at the sensor.

        The screen image is blurred (dark beyond its edges), sampled bilinearly at s x s
        sub-samples per pixel, averaged, scaled by the vignetted gain; plus ambient.
        """
        mean = self._prepare().sample(display_linear)
        assert self._gain is not None
        return mean * self._gain + np.float32(self.ambient)

    def truth(self) -> dict[str, Any]:
        """Ground truth of this setup (arrays (H,W); the caller gets its own copies).

        x_true/y_true: screen px seen by the pixel centers (float64, NaN if none);
        visible: all sub-samples of the pixel see the screen (visible_center: the center);
        edge_distance_px: distance of the seen point from the screen's border (pixels
        within a few blur widths of it mix in the dark bezel); blur_x/y: Gaussian-equivalent
        width (screen px) of everything that lowers modulation along that axis, the
        optical blur, the pixel footprint (sub-sample spread, footprint_sigma_*) and the
        bilinear interpolation of screen pixels (interpolation_sigma_*). The bilinear
        sampling also biases positions by less than 0.004 screen px for periods >= 16 px.
        """
        if self._truth is None:
            self._truth = self._compute_truth()
        return {k: v.copy() if isinstance(v, np.ndarray) else v for k, v in self._truth.items()}

    def _compute_truth(self) -> dict[str, Any]:
        """Build the truth dictionary (see `truth`)."""
        self._prepare()
        x, y = screen_points(self.camera, self.pose, self.screen, panel=self.panel)
        # Footprint of a pixel on the screen: Jacobian of (x, y) over (u, v).
        jxu, jxv = np.gradient(x, axis=1), np.gradient(x, axis=0)
        jyu, jyv = np.gradient(y, axis=1), np.gradient(y, axis=0)
        s = self.supersample
        box_var = (s * s - 1) / (12.0 * s * s)  # variance of s equally spaced sub-samples
        foot_x = np.sqrt(box_var * (jxu**2 + jxv**2))
        foot_y = np.sqrt(box_var * (jyu**2 + jyv**2))
        blur2 = self.blur_sigma_screen_px**2
        interp_x, interp_y = self._prepare().interpolation_variance()
        w_s, h_s = self.screen.width_px, self.screen.height_px
        edge = np.minimum(np.minimum(x + 0.5, w_s - 0.5 - x), np.minimum(y + 0.5, h_s - 0.5 - y))
        assert self._visible is not None and self._gain is not None
        return {
            "x_true": x,
            "y_true": y,
            "visible": self._visible,
            "visible_center": np.isfinite(x),
            "blur_sigma_screen_px": self.blur_sigma_screen_px,
            "footprint_sigma_x": foot_x,
            "footprint_sigma_y": foot_y,
            "interpolation_sigma_x": np.sqrt(interp_x),
            "interpolation_sigma_y": np.sqrt(interp_y),
            "blur_x": np.sqrt(blur2 + foot_x**2 + interp_x),
            "blur_y": np.sqrt(blur2 + foot_y**2 + interp_y),
            "edge_distance_px": edge,
            "vignetting": vignetting_map(self.camera, self.vignetting),
            "irradiance_gain": self._gain,
            "pose": self.pose,
            "panel": self.panel or PanelShape(),
        }
