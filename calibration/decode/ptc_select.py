"""Order statistics of the photon-transfer line (ptc_fit.py) without full sorts where a few
ranks are needed: quantiles read off sorted levels, a sorted array less some values, pixels
grouped by bin and each bin's median. Each gives exactly what the plain NumPy call gives
(`np.quantile`, `np.sort`, `np.argsort(kind="stable")`, `np.median`); the compiled passes
(ptc_kernels.py) run only where numba is already loaded (a process that decodes large
images), never importing it for a small decode (~0.5 s of CPU)."""

from __future__ import annotations

import functools
import sys
from types import ModuleType
from typing import Any

import numpy as np
from scipy.special import gammaincinv


def compiled() -> ModuleType | None:
    """ptc_kernels where numba is loaded in this process, else None (the NumPy path)."""
    if "numba" not in sys.modules:
        return None
    from calibration.decode import ptc_kernels

    return ptc_kernels


@functools.lru_cache(maxsize=8)
def chi2_median_ratios(top: int) -> np.ndarray:
    """`chi2.median(d) / d` for d = 1..top (gammaincinv is the costly part)."""
    dofs = np.arange(1, top + 1)
    median = 2.0 * gammaincinv(dofs / 2.0, 0.5)  # chi-square medians
    out = median / dofs
    out.flags.writeable = False
    return out


def variance_ratio(rss: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """`rss/dof` over each pixel's chi-square median `chi2.median(dof)/dof` (integer dof >=
    1): its median over pixels estimates the variance, also where dof differ (clipped steps
    leave fewer), and ignores the few pixels with model errors."""
    return rss / dof / chi2_median_ratios(int(dof.max()))[dof - 1]


def sorted_quantiles(ordered: np.ndarray, q: np.ndarray) -> np.ndarray:
    """`np.quantile(ordered, q)` (method "linear") of sorted, finite `ordered`: the same
    neighbours and NumPy's own interpolation arithmetic, without its partition (~4 ms)."""
    n = ordered.size
    virtual = (n - 1) * q
    previous = np.floor(virtual)
    following = previous + 1
    above = virtual >= n - 1
    previous[above], following[above] = -1, -1
    previous, following = previous.astype(np.intp), following.astype(np.intp)
    gamma = np.asanyarray(virtual - previous, dtype=virtual.dtype)
    a, b = ordered[previous], ordered[following]
    diff = b - a
    out = np.add(a, diff * gamma)
    np.subtract(b, diff * (1 - gamma), out=out, where=gamma >= 0.5, casting="unsafe")
    return out


def sorted_without(ordered: np.ndarray, removed: np.ndarray) -> np.ndarray | None:
    """`np.sort` of the levels once `removed` (some of them) are taken out, from their sorted
    `ordered`: the same values in the same order. None where levels are zero: NumPy's SIMD
    sort may give zeros either sign (its min/max of -0 and +0), so a fresh sort decides."""
    if np.searchsorted(ordered, 0.0) != np.searchsorted(ordered, 0.0, side="right"):
        return None
    values, counts = np.unique(removed, return_counts=True)
    first = np.repeat(np.searchsorted(ordered, values), counts)
    nth = np.arange(removed.size) - np.repeat(np.cumsum(counts) - counts, counts)
    return np.delete(ordered, first + nth)


def group_by_level(m: np.ndarray, inner: np.ndarray, lo: float,
                   hi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levels `m` (from `lo` to `hi`) grouped by bin (inner edges `inner`, a level at an edge
    above it): the stable order, each bin's first position (and the end), the levels in that
    order."""
    kernels = compiled()
    if kernels is not None:
        return kernels.group_by_level(m, inner, lo, hi)
    # each level's bin, as clip(searchsorted(edges, m, "right") - 1, 0, len(edges) - 2): the
    # inner edges at or below it (a few vectorized passes instead of a branchy search)
    which = np.zeros(m.shape, dtype=np.int16)
    for edge in inner:
        which += m >= edge
    order = np.argsort(which, kind="stable")  # (radix) bins contiguous
    return order, np.searchsorted(which[order], np.arange(inner.size + 2)), m[order]


def bin_ratios(rss: np.ndarray, dof: np.ndarray, good: np.ndarray, order: np.ndarray) -> np.ndarray:
    """`ptc_fit.variance_ratio(rss[good], rint(dof[good]))[order]` (one pass where compiled)."""
    kernels, top = compiled(), float(np.max(dof)) if dof.size else 0.0
    if kernels is not None and 1.0 <= top < 1e6:
        out, ok = kernels.binned_ratios(rss, dof, np.ascontiguousarray(good), order,
                                        chi2_median_ratios(round(top)))
        if ok:
            return out
    return variance_ratio(rss[good], np.rint(dof[good]).astype(np.int64))[order]


def bin_medians(values: np.ndarray, bins: list[slice], line: Any = None,
                m: np.ndarray | None = None) -> np.ndarray:
    """`np.median(values[b])` for each bin `b` (of `values / line.variance(m)` where a
    LinearVariance `line` is given), as float64: np.median's middle element (odd size) or
    the mean of its middle pair (even), NaN for a bin holding a NaN."""
    kernels = compiled()
    if line is not None and (kernels is None or not line.floor > 0):
        values, line = values / line.variance(m), None  # (NumPy's maximum: zeros' signs)
    if kernels is None or values.dtype != np.float64:
        return np.array([float(np.median(values[b])) for b in bins])
    starts = np.array([b.start for b in bins], dtype=np.int64)
    stops = np.array([b.stop for b in bins], dtype=np.int64)
    if line is None:
        m, params = values, np.zeros(0, values.dtype)
    else:
        params = np.array([line.offset, line.slope, line.floor], dtype=m.dtype)
    lo, hi = kernels.middle_pairs(values, starts, stops, m, params)
    # np.mean of the pair: their sum, halved
    return np.where((stops - starts) % 2 == 1, lo, (lo + hi) / 2)
