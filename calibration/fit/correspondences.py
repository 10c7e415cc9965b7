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


# A decoded value this many sigmas (plus twice the local spread) from its 3x3 median is an outlier.
_OUTLIER_SIGMAS = 6.0


def _neighbourhood(a: np.ndarray) -> np.ndarray:
    """(9, H, W) stack of each pixel's 3x3 neighbourhood (NaN outside the image)."""
    p = np.pad(a, 1, constant_values=np.nan)
    h, w = a.shape
    return np.stack([p[dv:dv + h, du:du + w] for dv in range(3) for du in range(3)])


def local_outliers(values: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Pixels whose decoded value disagrees with the median of their 3x3 neighbourhood.

    The decoded screen coordinate is a smooth function of the pixel, so the neighbourhood
    median predicts it (exactly where it is locally linear); a gross decoding error
    (wrong period, reflection) stands out by far more than its sigma.
    """
    stack = _neighbourhood(values)
    med = _nanmedian0(stack)
    spread = _nanmedian0(np.abs(stack - med))
    with np.errstate(invalid="ignore"):
        return np.abs(values - med) > _OUTLIER_SIGMAS * sigma + 2.0 * spread


def _nanmedian0(stack: np.ndarray) -> np.ndarray:
    """Median over axis 0 ignoring NaN (sort-based; much faster than np.nanmedian)."""
    srt = np.sort(stack, axis=0)  # NaN sorts last
    n = np.sum(np.isfinite(stack), axis=0)
    lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[None], axis=0)[0]
    hi = np.take_along_axis(srt, np.maximum(n // 2, 0)[None], axis=0)[0]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def point_set(maps: DecodedMaps, screen: ScreenGeometry, *, reject_outliers: bool = True
              ) -> PointSet:
    """All trusted, finite correspondences of one pose, minus local decoding outliers."""
    keep = maps.mask & np.isfinite(maps.x) & np.isfinite(maps.y)
    if reject_outliers:
        x = np.where(keep, maps.x, np.nan)
        y = np.where(keep, maps.y, np.nan)
        keep &= ~local_outliers(x, maps.sigma_x) & ~local_outliers(y, maps.sigma_y)
    v, u = np.nonzero(keep)
    pixels = np.stack([u, v], axis=1).astype(np.float64)
    scr = np.stack([maps.x[v, u], maps.y[v, u]], axis=1)
    sig = np.stack([maps.sigma_x[v, u], maps.sigma_y[v, u]], axis=1).astype(np.float64)
    ok = np.all(np.isfinite(sig), axis=1) & np.all(sig > 0, axis=1)
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
