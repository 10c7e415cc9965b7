"""Decoded maps + screen geometry -> weighted, spatially uniform point sets for the fits."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import ScreenGeometry


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


# Comparators of an optimal 25-comparator sorting network for 9 values (0-1 principle
# checked in tests): the 3x3 medians sort planes element-wise instead of a strided sort.
_SORT9 = ((0, 1), (3, 4), (6, 7), (1, 2), (4, 5), (7, 8), (0, 1), (3, 4), (6, 7), (0, 3),
          (3, 6), (0, 3), (1, 4), (4, 7), (1, 4), (2, 5), (5, 8), (2, 5), (1, 3), (5, 7),
          (2, 6), (4, 6), (2, 4), (2, 3), (5, 6))
_BLOCK_ROWS = 16  # image rows per block: the (9, rows, W) planes stay in cache


def _sort9(planes: np.ndarray, scratch: np.ndarray) -> None:
    """Sort a (9, ...) array in place along axis 0 (no NaN: use inf for missing values)."""
    for i, j in _SORT9:
        np.minimum(planes[i], planes[j], out=scratch)
        np.maximum(planes[i], planes[j], out=planes[j])
        planes[i] = scratch


def _median_of_sorted(srt: np.ndarray, n: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                      out: np.ndarray) -> np.ndarray:
    """`out` = the median of the first `n` values along axis 0 of the sorted (9, ...) `srt`,
    NaN where n is 0 (`lo`, `hi`: int scratch shaped like n)."""
    np.subtract(n, 1, out=lo)
    np.floor_divide(lo, 2, out=lo)
    np.maximum(lo, 0, out=lo)
    np.floor_divide(n, 2, out=hi)
    out[...] = np.take_along_axis(srt, lo[None], axis=0)[0]
    out += np.take_along_axis(srt, hi[None], axis=0)[0]
    out *= 0.5
    out[n == 0] = np.nan
    return out


def local_outliers(values: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Pixels whose decoded value disagrees with the median of their 3x3 neighbourhood.

    The decoded screen coordinate is a smooth function of the pixel, so the neighbourhood
    median predicts it (exactly where it is locally linear); a gross decoding error
    (wrong period, reflection) stands out by far more than its sigma. Medians and the
    median absolute deviation ignore NaN (missing) neighbours and pixels outside the image.
    Row blocks reuse their buffers (no fresh pages per block).
    """
    h, w = values.shape
    padded = np.pad(values, 1, constant_values=np.nan)
    out = np.zeros((h, w), dtype=bool)
    rows = min(_BLOCK_ROWS, h)
    stack, dev = np.empty((9, rows, w)), np.empty((9, rows, w))
    finite = np.empty((9, rows, w), dtype=bool)
    n, lo, hi = (np.empty((rows, w), dtype=np.intp) for _ in range(3))
    med, spread, tmp = np.empty((rows, w)), np.empty((rows, w)), np.empty((rows, w))
    for r0 in range(0, h, rows):
        b = min(rows, h - r0)
        st, dv_, fi, nb = stack[:, :b], dev[:, :b], finite[:, :b], n[:b]
        for k in range(9):
            st[k] = padded[r0 + k // 3:r0 + k // 3 + b, k % 3:k % 3 + w]
        np.isfinite(st, out=fi)
        fi.sum(axis=0, out=nb)
        st[~fi] = np.inf
        _sort9(st, tmp[:b])
        _median_of_sorted(st, nb, lo[:b], hi[:b], med[:b])
        with np.errstate(invalid="ignore"):
            np.subtract(st, med[:b], out=dv_)  # the finite ones: the same n values, unsorted
            np.abs(dv_, out=dv_)
            dv_[~np.isfinite(dv_)] = np.inf
            _sort9(dv_, tmp[:b])
            _median_of_sorted(dv_, nb, lo[:b], hi[:b], spread[:b])
            out[r0:r0 + b] = (np.abs(values[r0:r0 + b] - med[:b])
                              > _OUTLIER_SIGMAS * sigma[r0:r0 + b] + 2.0 * spread[:b])
    return out


def point_set(maps: DecodedMaps, screen: ScreenGeometry, *, reject_outliers: bool = True
              ) -> PointSet:
    """All trusted, finite correspondences of one pose, minus local decoding outliers."""
    keep = maps.mask & np.isfinite(maps.x) & np.isfinite(maps.y)
    if reject_outliers:
        x = np.where(keep, maps.x, np.nan)
        y = np.where(keep, maps.y, np.nan)
        keep &= ~local_outliers(x, maps.sigma_x) & ~local_outliers(y, maps.sigma_y)
    with np.errstate(invalid="ignore"):  # (finite, positive sigmas; NaN compares False)
        for sig in (maps.sigma_x, maps.sigma_y):
            keep &= (sig > 0) & (sig < np.inf)
    v, u = np.nonzero(keep)
    pixels = np.column_stack([u, v]).astype(np.float64)
    scr = np.column_stack([maps.x[keep], maps.y[keep]])
    sig = np.column_stack([maps.sigma_x[keep], maps.sigma_y[keep]]).astype(np.float64)
    return PointSet(pixels, scr, sig, screen.pitch_mm)


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
