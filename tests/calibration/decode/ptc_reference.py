"""The photon-transfer line as it was before issue 15g (plain sorts, `np.quantile`, one
`np.median` per bin, `np.column_stack`): the reference the faster product code must match
bit for bit (tests/calibration/decode/test_ptc_fast.py, benchmarks/noise_line.py)."""

from __future__ import annotations

import itertools

import numpy as np
from scipy.special import gammaincinv

from calibration.decode.ptc_fit import LevelBins, _weighted_line, usable_pixels


def variance_ratio(rss, dof):
    """`rss/dof` over each pixel's chi-square median (the pre-15g code)."""
    dofs = np.arange(1, int(dof.max()) + 1)
    median = 2.0 * gammaincinv(dofs / 2.0, 0.5)
    return rss / dof / (median / dofs)[dof - 1]


def level_bins(mean, rss, dof, bins=16, max_pixels=1 << 19):
    """The level bins (the pre-15g code)."""
    usable = usable_pixels(mean, rss, dof)
    if usable.size < 64:
        return None
    good = usable[:: max(1, usable.size // max_pixels)]
    m = mean[good]
    ordered = np.sort(m)
    edges = np.unique(np.quantile(ordered, np.linspace(0.0, 1.0, bins + 1)))
    which = np.zeros(m.shape, dtype=np.int16)
    for edge in edges[1:-1]:
        which += m >= edge
    order = np.argsort(which, kind="stable")
    m = m[order]
    bounds = np.searchsorted(which[order], np.arange(len(edges)))
    bins_ = [slice(int(lo), int(hi)) for lo, hi in itertools.pairwise(bounds) if hi - lo >= 16]
    if len(bins_) < 4:
        return None
    count = np.array([b.stop - b.start for b in bins_], dtype=np.float64)
    x = np.array([float(np.mean(ordered[_middle(b)])) for b in bins_])
    return LevelBins(usable, good, order, bins_, x, count, m, ordered, edges, bounds)


def _middle(b):
    half = b.start + (b.stop - b.start) // 2
    return slice(half, half + 1) if (b.stop - b.start) % 2 else slice(half - 1, half + 1)


def binned_line(binned, rss, dof, floor, low):
    """The line through the bins (the pre-15g code)."""
    if binned is None:
        return None
    good, bins_, x, count, m = binned.good, binned.bins, binned.x, binned.count, binned.m
    ratio = variance_ratio(rss[good], np.rint(dof[good]).astype(np.int64))[binned.order]
    line = None
    for _ in range(2):
        rel = ratio if line is None else ratio / line.variance(m)
        at = np.ones(x.shape) if line is None else line.variance(x)
        y = np.array([float(np.median(rel[b])) for b in bins_]) * at
        ok = y > 0
        if ok.sum() < 4:
            return line
        line = _weighted_line(x[ok], y[ok], count[ok], floor, low)
    return line


def harmonic_leak(rss, dof, level, power, first, max_rows=1 << 16):
    """The display harmonic's r^2 per set (the pre-15g code)."""
    if first is None or not power.any() or rss.size < 1000:
        return None
    step = max(1, rss.size // max_rows)
    rss, dof, level, power = rss[::step], dof[::step], level[::step], power[:, ::step]
    var = np.asarray(first.variance(level), dtype=np.float64)
    ok = rss < 10.0 * dof * var
    w = 1.0 / (dof * var)[ok]
    design = np.column_stack([dof[ok] * w, dof[ok] * level[ok] * w, *(p[ok] * w for p in power)])
    used = np.flatnonzero(np.abs(design).sum(axis=0) > 0)
    coef = np.zeros(design.shape[1])
    coef[used] = np.linalg.lstsq(design[:, used], rss[ok] * w, rcond=None)[0]
    scatter = np.sum((design @ coef - rss[ok] * w) ** 2) / max(design.shape[0] - used.size, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.sqrt(scatter / np.einsum("ij,ij->j", design, design))
    r2 = np.where(coef[2:] > 5.0 * err[2:], coef[2:], 0.0)
    share = float(np.sum(r2 * power[:, ok].mean(axis=1)) / np.mean(dof[ok] * var[ok]))
    return r2 if share >= 0.01 else None


def residual_line(mean, rss, dof, power, floor, dark):
    """`noise.residual_line` (the pre-15g code)."""
    from calibration.models.blas_threads import single_thread_blas

    with single_thread_blas(scipy=False):
        low = float(np.median(dark)) if dark.size else None
        binned = level_bins(mean, rss, dof)
        line = binned_line(binned, rss, dof, floor, low)
        leak = harmonic_leak(rss, dof, mean, power, line)
        if leak is None:
            return line, None
        rss = np.maximum(rss - leak.astype(np.float32) @ power, 0.0)
        if binned is None or not np.array_equal(binned.usable, usable_pixels(mean, rss, dof)):
            binned = level_bins(mean, rss, dof)
        return binned_line(binned, rss, dof, floor, low), [float(r2) for r2 in leak]
