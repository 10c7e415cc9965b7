"""A real screen: a shaped emitting panel behind a refracting cover glass, traced exactly.

Screen frame (mm): x, y along the panel's pixel rows/columns, z into the screen (away from
the viewer); a bare flat panel has its pixels on z = 0, today's ideal screen.
- Shape: the emitting layer lies at z = z_s(x, y) = bow_x (xi^2 - 1/3) + bow_y (eta^2 - 1/3)
  + twist xi eta, with xi, eta in [-1, 1] over the panel's extent. The bow is the sag from
  the panel's center to its edge midpoints (positive: center towards the viewer); the
  terms have zero mean and zero tilt over the panel, so a pose absorbs no part of them.
- Glass: a flat plate of index n whose front surface is at z = -glass_mm; the medium
  between that surface and the emitting layer has index n (an optically bonded cover).
  A ray refracts once, at the front surface (Snell), then runs straight to the panel.
A pixel (x, y) of the panel emits from (x * pitch_x, y * pitch_y, z_s) (the in-plane
stretch of a bow of a millimetre over a panel is below 1e-5 mm and ignored).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.shared.plan import ScreenGeometry

# Fixed-point iterations for the ray-panel intersection (slopes << 1 converge in a few).
_MAX_ITERS = 50
_TOL_MM = 1e-12


@dataclass(frozen=True)
class PanelShape:
    """Bow/twist of the emitting layer (mm) and the cover glass (thickness mm, index)."""

    bow_x_mm: float = 0.0
    bow_y_mm: float = 0.0
    twist_mm: float = 0.0
    glass_mm: float = 0.0
    glass_index: float = 1.52

    def __post_init__(self) -> None:
        """Validate the fields (errors name the field and what was expected)."""
        for name in ("bow_x_mm", "bow_y_mm", "twist_mm", "glass_mm", "glass_index"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"PanelShape.{name}: expected a finite number")
        if self.glass_mm < 0:
            raise ValueError(f"PanelShape.glass_mm: expected >= 0, got {self.glass_mm}")
        if self.glass_index < 1:
            raise ValueError(f"PanelShape.glass_index: expected >= 1, got {self.glass_index}")
        sag = (abs(self.bow_x_mm) + abs(self.bow_y_mm)) / 3 + abs(self.twist_mm)
        if self.glass_mm > 0 and sag >= self.glass_mm:
            raise ValueError(
                f"PanelShape: the panel (up to {sag:.3g} mm in front of z = 0) must lie behind "
                f"the glass front surface at z = -{self.glass_mm} mm")

    @property
    def is_ideal(self) -> bool:
        """True for today's screen: flat, bare, pixels at z = 0."""
        return self.bow_x_mm == self.bow_y_mm == self.twist_mm == self.glass_mm == 0.0

    def _normalized(self, screen: ScreenGeometry, x_mm: np.ndarray, y_mm: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, float, float]:
        """(xi, eta) in [-1, 1] over the panel and the half extents (mm)."""
        ax = 0.5 * screen.width_px * screen.pitch_mm[0]
        ay = 0.5 * screen.height_px * screen.pitch_mm[1]
        xi = (x_mm - 0.5 * (screen.width_px - 1) * screen.pitch_mm[0]) / ax
        eta = (y_mm - 0.5 * (screen.height_px - 1) * screen.pitch_mm[1]) / ay
        return xi, eta, ax, ay

    def depth_mm(self, screen: ScreenGeometry, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """z of the emitting layer (mm) at panel coordinates (x, y) mm."""
        xi, eta, _, _ = self._normalized(screen, x_mm, y_mm)
        return (self.bow_x_mm * (xi * xi - 1 / 3) + self.bow_y_mm * (eta * eta - 1 / 3)
                + self.twist_mm * xi * eta)

    def trace(self, screen: ScreenGeometry, origins: np.ndarray, dirs: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays in the screen frame (...,3) -> the panel point (x, y mm) they reach, and `ok`.

        `ok` is False where the ray starts behind the glass front surface or does not
        travel into the screen. Bare panels (glass_mm = 0) refract nowhere.
        """
        o, d = np.asarray(origins, np.float64), np.asarray(dirs, np.float64)
        front = -self.glass_mm
        with np.errstate(divide="ignore", invalid="ignore"):
            q = d[..., :2] / d[..., 2:3]  # lateral slope of the incoming ray
            p = o[..., :2] + (front - o[..., 2:3]) * q  # where it meets the front surface
            if self.glass_mm > 0:
                n2 = self.glass_index**2
                m = q / np.sqrt(n2 + (n2 - 1) * np.sum(q * q, -1, keepdims=True))
            else:
                m = q
        ok = (d[..., 2] > 0) & (o[..., 2] < front)
        hit = p - front * m
        with np.errstate(over="ignore", invalid="ignore"):  # grazing rays: inf/NaN, not ok
            for _ in range(_MAX_ITERS):
                z = self.depth_mm(screen, hit[..., 0], hit[..., 1])
                new = p + (z - front)[..., None] * m
                step = np.nanmax(np.abs(new - hit), initial=0.0)
                hit = new
                if step < _TOL_MM:
                    break
        return hit[..., 0], hit[..., 1], ok


def lateral_shift_mm(theta_rad: float, glass_mm: float, index: float) -> float:
    """Sideways move of the seen point through a flat plate, d (tan t - tan t') (PHYSICS 7)."""
    inner = np.arcsin(np.sin(theta_rad) / index)
    return float(glass_mm * (np.tan(theta_rad) - np.tan(inner)))
