"""Decoded maps + screen geometry -> weighted, spatially uniform point sets for the fits."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.maps import DecodedMaps
from calibration.plan import ScreenGeometry


@dataclass
class PointSet:
    """Pixel <-> screen correspondences of one pose (mm on the screen plane, z = 0)."""

    pixels: np.ndarray  # (N, 2) camera px (u, v)
    screen_px: np.ndarray  # (N, 2) decoded screen px (x, y)
    sigma_px: np.ndarray  # (N, 2) 1-sigma of screen_px, screen px
    pitch_mm: tuple[float, float]

    @property
    def screen_mm(self) -> np.ndarray:
        """(N, 3) screen points in mm: (x * pitch_x, y * pitch_y, 0)."""
        n = self.screen_px.shape[0]
        return np.column_stack([self.screen_px[:, 0] * self.pitch_mm[0],
                                self.screen_px[:, 1] * self.pitch_mm[1], np.zeros(n)])

    def __len__(self) -> int:
        """Number of correspondences."""
        return int(self.pixels.shape[0])

    def subset(self, keep: np.ndarray) -> PointSet:
        """The correspondences selected by a boolean mask or index array."""
        return PointSet(self.pixels[keep], self.screen_px[keep], self.sigma_px[keep], self.pitch_mm)


def point_set(maps: DecodedMaps, screen: ScreenGeometry) -> PointSet:
    """All trusted, finite correspondences of one pose."""
    pixels, scr, sig = maps.correspondences()
    ok = np.all(np.isfinite(scr), axis=1) & np.all(np.isfinite(sig), axis=1) & np.all(sig > 0, 1)
    return PointSet(pixels[ok], scr[ok], sig[ok], screen.pitch_mm)


def subsample(points: PointSet, max_points: int) -> PointSet:
    """At most ~max_points, spread evenly over the image: the best-sigma pixel of each grid cell.

    Uniform spatial coverage keeps the distortion well constrained at the image edges,
    and taking the lowest-sigma pixel per cell keeps the most informative data.
    """
    n = len(points)
    if n <= max_points:
        return points
    u, v = points.pixels[:, 0], points.pixels[:, 1]
    span = max(float(np.ptp(u)) + 1, 1.0) * max(float(np.ptp(v)) + 1, 1.0)
    cell = max(float(np.sqrt(span / max_points)), 1.0)
    iu = np.floor((u - u.min()) / cell).astype(np.int64)
    iv = np.floor((v - v.min()) / cell).astype(np.int64)
    key = iv * (int(iu.max()) + 1) + iu
    quality = np.hypot(points.sigma_px[:, 0], points.sigma_px[:, 1])
    order = np.lexsort((quality, key))
    _, first = np.unique(key[order], return_index=True)
    return points.subset(np.sort(order[first]))
