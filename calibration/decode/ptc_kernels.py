"""Compiled passes of the photon-transfer line (ptc_select.py wraps them): pixels grouped by
level bin, each bin's exact middle pair, the variance ratios in bin order and the rows of the
display-harmonic fit, each in one or two passes instead of NumPy's sorts, selections and
temporaries. Every value is the one the NumPy code computes, bit for bit (the same IEEE
operations on the same types: float32 where NumPy keeps float32, no fastmath).

These kernels call only each other, so numba's cache, keyed on this file, stays right on its
own: they are declared through `_kernel`, outside kernel_cache's digest of the finish kernels
(an edit here does not recompile those, nor theirs these)."""

from __future__ import annotations

import numpy as np
from numba import njit

_kernel = njit(cache=True, error_model="numpy", nogil=True)
_BUCKETS = 4096  # level buckets of group_by_level's bin table
_SAMPLE = 512  # levels sampled per bin to bracket its middle pair
_MARGIN = 32  # sample ranks either side of the middle (~3 standard errors of its rank)


@_kernel
def group_by_level(m, inner, lo, hi):
    """NumPy's `argsort(which, kind="stable")` of each level's bin `which` (the number of
    `inner` edges at or below it, compared in float64), the first position of each bin and
    the levels in that order: the bins (`_bins`), one count and one scatter."""
    n, nb = m.size, inner.size + 1
    which = _bins(m, inner, lo, hi)
    bounds = np.zeros(nb + 1, np.int64)
    for i in range(n):
        bounds[which[i] + 1] += 1
    for b in range(nb):
        bounds[b + 1] += bounds[b]
    at = bounds[:nb].copy()
    order, ordered = np.empty(n, np.int64), np.empty(n, m.dtype)
    for i in range(n):
        p = at[which[i]]
        order[p], ordered[p] = i, m[i]
        at[which[i]] = p + 1
    return order, bounds, ordered


@_kernel
def _bins(m, inner, lo, hi):
    """Each level's bin from a table over `_BUCKETS` even buckets of [lo, hi]: the bucket
    `floor((v - lo) * scale)` never decreases with v, so a bucket's levels are all at or
    above the edges of lower buckets and below those of higher ones; the one edge inside
    its own bucket, if any, is compared branch-free (several: each counted)."""
    scale = _BUCKETS / (hi - lo) if hi > lo else 0.0
    below = np.zeros(_BUCKETS + 1, np.int32)  # edges in lower buckets
    inside = np.full(_BUCKETS + 1, np.inf)  # the edge in the bucket
    several = np.zeros(_BUCKETS + 1, np.bool_)
    for e in range(inner.size):  # (ascending)
        x = (inner[e] - lo) * scale
        if not x <= _BUCKETS:
            continue  # (above every bucket)
        first = int(np.floor(x)) if x >= 0 else -1
        if first >= 0:
            several[first] = inside[first] != np.inf
            inside[first] = inner[e]
        for b in range(first + 1, _BUCKETS + 1):
            below[b] += 1
    which = np.empty(m.size, np.int32)
    for i in range(m.size):
        v = np.float64(m[i])
        x = (v - lo) * scale
        b = min(max(int(x), 0), _BUCKETS) if x == x else 0
        w = below[b] + (v >= inside[b])
        if several[b] or not (x >= 0 and x <= _BUCKETS):  # (rare: count every edge)
            w = 0
            for e in range(inner.size):
                w += v >= inner[e]
        which[i] = w
    return which


@_kernel
def _select(x, n, k):
    """The `k`-th smallest of `x[:n]` (no NaN; `x` reordered): Hoare quickselect, sorting the
    rest after many rounds (a bad pivot sequence)."""
    lo, hi, rounds = 0, n - 1, 0
    while hi > lo:
        rounds += 1
        if hi - lo < 16 or rounds > 64:
            x[lo:hi + 1] = np.sort(x[lo:hi + 1])
            break
        a, b, c = x[lo], x[(lo + hi) >> 1], x[hi]
        pivot = max(min(a, b), min(max(a, b), c))  # median of three
        i, j = lo, hi
        while i <= j:
            while x[i] < pivot:
                i += 1
            while x[j] > pivot:
                j -= 1
            if i <= j:
                x[i], x[j] = x[j], x[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return x[k]


@_kernel
def _pair(x, n, k1):
    """The `k1`-th and `k1 + 1`-th smallest of `x[:n]` (no NaN)."""
    first = _select(x, n, k1)
    second = x[k1 + 1]
    for i in range(k1 + 2, n):
        second = min(second, x[i])
    return first, second


@_kernel
def _relative(values, i, m, line):
    """`values[i]`, over the `line` (offset, slope, floor in `m`'s type, as NumPy's weak
    scalars) at level `m[i]` where `line` is given: `ratio / LinearVariance.variance(m)`."""
    if line.size == 0:
        return values[i]
    var = line[0] + line[1] * m[i]
    return values[i] / np.float64(var if (var >= line[2] or var != var) else line[2])


@_kernel
def middle_pairs(values, starts, stops, m, line):
    """Per bin `values[starts[j]:stops[j]]` (each over the `line` at its level `m` where
    `line` is not empty), the elements of rank `(n - 1) // 2` and `n // 2` (np.median's
    middle pair); NaN where the bin holds a NaN. A strided sample brackets the middle; one
    branch-free pass counts the values below the bracket and keeps those in it, and a
    quickselect of those finds the pair (the whole bin where the bracket missed)."""
    nb = starts.size
    lo, hi = np.empty(nb), np.empty(nb)
    buf = np.empty(np.max(stops - starts) + 1)
    sample = np.empty(_SAMPLE)
    for j in range(nb):
        a, n = starts[j], stops[j] - starts[j]
        k1, odd = (n - 1) // 2, n % 2 == 1
        below, kept, nan = 0, 0, False
        if n > 8 * _SAMPLE:
            stride = n // _SAMPLE
            for t in range(_SAMPLE):
                sample[t] = _relative(values, a + t * stride, m, line)
            sample.sort()
            at = (k1 * _SAMPLE) // n
            low = sample[max(at - _MARGIN, 0)]
            high = sample[min(at + _MARGIN, _SAMPLE - 1)]
            for i in range(a, a + n):
                v = _relative(values, i, m, line)
                below += v < low
                buf[kept] = v
                kept += (v >= low) & (v <= high)
                nan |= v != v
            if not (below <= k1 and k1 + 1 < below + kept):  # missed: the whole bin
                below, kept = 0, 0
        if kept == 0:
            for i in range(n):
                buf[i] = _relative(values, a + i, m, line)
                nan |= buf[i] != buf[i]
            kept = n
        if nan:
            lo[j], hi[j] = np.nan, np.nan
        elif odd:
            lo[j] = _select(buf, kept, k1 - below)
            hi[j] = lo[j]
        else:
            lo[j], hi[j] = _pair(buf, kept, k1 - below)
    return lo, hi


@_kernel
def binned_ratios(rss, dof, good, order, table):
    """`variance_ratio(rss[good], rint(dof[good]))[order]` with `table` the chi-square medians
    over dof (1, 2, ...); False when a dof falls outside the table (NumPy decides then)."""
    out = np.empty(order.size)
    for p in range(order.size):
        g = good[order[p]]
        d = np.rint(dof[g])
        if not (d >= 1 and d <= table.size):
            return out, False
        out[p] = np.float64(rss[g]) / np.float64(d) / table[np.int64(d) - 1]
    return out, True


@_kernel
def leak_rows(rss, dof, level, power, step, line):
    """harmonic_leak's rows, every `step`-th pixel whose rss is under 10x the first `line`
    (offset, slope, floor as float32, as NumPy's weak scalars): the weighted design, its
    right-hand side, `dof * var` and the pixels' harmonic powers, and per column whether it
    is used (nonzero, no NaN); the rows kept are the first `k` of each."""
    n, sets = (rss.size + step - 1) // step, power.shape[0]
    design, rhs, dv = np.empty((n, sets + 2)), np.empty(n), np.empty(n)
    kept_power = np.empty((sets, n), power.dtype)
    nonzero, nan = np.zeros(sets + 2, np.bool_), np.zeros(sets + 2, np.bool_)
    offset, slope, floor = line[0], line[1], line[2]
    k = 0
    for r in range(n):
        i = r * step
        d, lv = dof[i], level[i]
        v = offset + slope * lv
        var = np.float64(v if (v >= floor or v != v) else floor)
        if not np.float64(rss[i]) < np.float64(np.float32(10.0) * d) * var:
            continue
        w = 1.0 / (np.float64(d) * var)
        design[k, 0] = np.float64(d) * w
        design[k, 1] = np.float64(d * lv) * w
        for s in range(sets):
            kept_power[s, k] = power[s, i]
            design[k, 2 + s] = np.float64(power[s, i]) * w
        for c in range(sets + 2):
            nonzero[c] |= design[k, c] != 0
            nan[c] |= design[k, c] != design[k, c]
        rhs[k], dv[k] = np.float64(rss[i]) * w, np.float64(d) * var
        k += 1
    return design, rhs, dv, kept_power, nonzero & ~nan, k



def warm_up() -> None:
    """Load (or compile, once per machine) each kernel with the decoder's argument types."""
    n = 64
    level = np.linspace(0.0, 200.0, n).astype(np.float32)
    ones = np.ones(n, np.float32)
    order, _, _ = group_by_level(level, np.array([50.0, 100.0]), 0.0, 200.0)
    ratio = np.linspace(1.0, 2.0, n)
    for m, line in ((ratio, np.zeros(0)), (level, np.ones(3, np.float32))):  # passes 1, 2
        middle_pairs(ratio, np.array([0, 32]), np.array([32, 64]), m, line)
    table = np.ones(2)
    table.flags.writeable = False  # (as ptc_select's cached table)
    binned_ratios(ones, ones, np.arange(n), order, table)
    power = np.asfortranarray(np.ones((2, n), np.float32))  # (the decoder's layout)
    leak_rows(ones, ones, level, power, 1, np.ones(3, np.float32))
