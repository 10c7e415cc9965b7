"""The photon-transfer line of the residual noise estimate: per-pixel residual variances
binned by mean level, a robust variance per bin, a weighted line through the bins
(noise.py `residual_line` uses it twice per decode, on the main thread after the last
frame, so its sorting and selections are done once where they can be)."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.decode.ptc_select import (
    bin_medians,
    bin_ratios,
    group_by_level,
    sorted_quantiles,
    sorted_without,
)


@dataclass(frozen=True)
class LinearVariance:
    """Noise variance linear in the mean level, `offset + slope * mean` (a photon-transfer
    line), never below `floor` (quantization). `offset` is the line at 0 DN: below zero
    for a sensor whose black level exceeds `read^2 * gain` (variance = read^2 + q^2/12 +
    (mean - black) / gain), so the floor bounds the line, not its intercept."""

    offset: float
    slope: float
    floor: float = 0.0

    def variance(self, mean_dn: Any) -> Any:
        """Noise variance (DN^2) at mean level `mean_dn`."""
        return np.maximum(self.offset + self.slope * mean_dn, self.floor)


def fit_photon_transfer(
    mean: np.ndarray,
    rss: np.ndarray,
    dof: np.ndarray,
    floor: float,
    bins: int = 16,
    max_pixels: int = 1 << 19,
    low: float | None = None,
) -> LinearVariance | None:
    """Fit the sensor's variance-versus-mean line to per-pixel cosine-fit residuals.

    Pixels are grouped into mean-level quantile bins; each bin's variance is the median of
    `rss/dof` over each pixel's chi-square median `chi2.median(dof)/dof` (pixels with
    clipped steps have fewer dof), which ignores the few pixels with model errors. A straight
    line through the bins (slope >= 0) gives every pixel a variance estimated from millions
    of residual degrees of freedom instead of its own handful; an even subsample of at most
    ~2 `max_pixels` pixels (~30000 per bin) is plenty. None when < 4 bins have data.
    """
    return binned_line(level_bins(mean, rss, dof, bins, max_pixels), rss, dof, floor, low)


@dataclass(frozen=True)
class LevelBins:
    """`fit_photon_transfer`'s level bins: `usable` pixels, `good` their even subsample,
    `order` putting each bin's pixels together, `bins` the slices of >= 16 of them, `x`
    their median levels, `count` their sizes, `m` the levels in `order`, `ordered` sorted,
    `edges` the bins' edges and `bounds` every bin's first position (and the end)."""

    usable: np.ndarray
    good: np.ndarray
    order: np.ndarray
    bins: list[slice]
    x: np.ndarray
    count: np.ndarray
    m: np.ndarray
    ordered: np.ndarray
    edges: np.ndarray
    bounds: np.ndarray


def usable_pixels(mean: np.ndarray, rss: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """Indices of the pixels a line can use. Pixels reading one constant value (rss 0: e.g.
    a black level under the noise) say nothing about it and would collapse the quantiles."""
    return np.flatnonzero(np.isfinite(mean) & np.isfinite(rss) & (dof >= 1) & (rss > 0))


def level_bins(mean: np.ndarray, rss: np.ndarray, dof: np.ndarray, bins: int = 16,
               max_pixels: int = 1 << 19, previous: LevelBins | None = None) -> LevelBins | None:
    """`fit_photon_transfer`'s mean-level quantile bins; None when < 4 can have data (no
    line). The residuals only choose the usable pixels: from `previous` bins of the same
    levels whose usable pixels include these (the display harmonic removed), the sorted
    levels are theirs less the pixels dropped (no sort), and where the edges stay, so does
    each pixel's bin (no grouping)."""
    usable = usable_pixels(mean, rss, dof)
    if usable.size < 64:
        return None
    if previous is not None and np.array_equal(previous.usable, usable):
        return previous
    good = usable[:: max(1, usable.size // max_pixels)]  # an even subsample bounds the work
    kept = _kept(previous, mean.size, usable, good)
    ordered = None if kept is None else sorted_without(
        previous.ordered, mean[previous.good[~kept]])
    if ordered is None:
        kept, ordered = None, np.sort(mean[good])  # (the order statistics: SIMD sort)
    edges = np.unique(sorted_quantiles(ordered, np.linspace(0.0, 1.0, bins + 1)))
    if kept is not None and np.array_equal(edges[1:-1], previous.edges[1:-1]):
        in_order = kept[previous.order]  # the same bins, less the pixels dropped
        order = (np.cumsum(kept) - 1)[previous.order[in_order]]
        bounds = np.concatenate([[0], np.cumsum(in_order)])[previous.bounds]
        m = previous.m[in_order]
    else:
        order, bounds, m = group_by_level(mean[good], edges[1:-1], float(ordered[0]),
                                          float(ordered[-1]))
    # a loop over 16 bins, not over pixels
    bins_ = [slice(int(lo), int(hi)) for lo, hi in itertools.pairwise(bounds) if hi - lo >= 16]
    if len(bins_) < 4:
        return None
    count = np.array([b.stop - b.start for b in bins_], dtype=np.float64)
    # each bin's levels are `ordered[b]`, sorted: np.median's own middle pair, its own mean
    x = np.array([float(np.mean(ordered[_middle(b)])) for b in bins_])
    return LevelBins(usable, good, order, bins_, x, count, m, ordered, edges, bounds)


def _kept(previous: LevelBins | None, size: int, usable: np.ndarray,
          good: np.ndarray) -> np.ndarray | None:
    """Which of `previous` bins' pixels are still `usable`, where both took every usable
    pixel and these are a subset of theirs; else None."""
    if previous is None or good.size != usable.size or \
            previous.good.size != previous.usable.size:
        return None
    still = np.zeros(size, dtype=bool)
    still[usable] = True
    kept = still[previous.usable]
    return kept if np.count_nonzero(kept) == usable.size else None


def _middle(b: slice) -> slice:
    """The middle element (odd size) or pair (even) of a bin's sorted levels, as np.median
    takes them from its partition."""
    half = b.start + (b.stop - b.start) // 2
    return slice(half, half + 1) if (b.stop - b.start) % 2 else slice(half - 1, half + 1)


def binned_line(binned: LevelBins | None, rss: np.ndarray, dof: np.ndarray, floor: float,
                low: float | None) -> LinearVariance | None:
    """`fit_photon_transfer`'s line through the `binned` pixels' variance ratios."""
    if binned is None:
        return None
    good, bins_, x, count, m = binned.good, binned.bins, binned.x, binned.count, binned.m
    ratio = bin_ratios(rss, dof, good, binned.order)
    line: LinearVariance | None = None
    for _ in range(2):
        # Second pass: each ratio over the first line at its own level, so a bin whose levels
        # (hence variances) span a factor of several still gives the line at its median level
        # (the plain median of such a mixture sat 6 % low in the darkest bin).
        at = np.ones(x.shape) if line is None else line.variance(x)
        y = bin_medians(ratio, bins_, line, m) * at
        ok = y > 0  # mostly constant readings (a black level under the noise) say nothing
        if ok.sum() < 4:  # about the line, and 1/y weights would be infinite
            return line
        line = _weighted_line(x[ok], y[ok], count[ok], floor, low)
    return line


def _weighted_line(x: np.ndarray, y: np.ndarray, w: np.ndarray, floor: float,
                   low: float | None) -> LinearVariance:
    """Line through bin variances `y` at levels `x` (`w` pixels each, relative errors), slope
    >= 0 and at or above `floor` from level `low` (default: the lowest bin) up."""
    wt = w / y**2  # the polyfit weights squared: relative errors of the bin medians
    slope, offset = np.polyfit(x, y, 1, w=np.sqrt(wt))
    low = float(x.min()) if low is None else min(float(low), float(x.min()))
    if slope < 0:
        slope, offset = 0.0, max(float(np.average(y, weights=w)), floor)
    elif offset + slope * low < floor:
        # Constrained least squares: the line at its floor at the lowest level seen, the slope
        # refitted. (Clamping the offset alone would lift the whole line where the levels span
        # a narrow range; pinning it at 0 DN instead of the lowest level would bend it where
        # a black level makes the true intercept negative.)
        dx = x - low
        slope = max(float(np.sum(wt * dx * (y - floor)) / max(np.sum(wt * dx * dx), 1e-300)), 0.0)
        offset = floor - slope * low
    return LinearVariance(offset=float(offset), slope=float(slope), floor=floor)
