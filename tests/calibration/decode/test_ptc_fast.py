"""The fast photon-transfer line (issue 15g: quantiles read off sorted levels, the sorted
levels reused after the harmonic is removed, compiled bin medians, ratios and harmonic rows)
gives bit for bit what the plain code gave (`ptc_reference`: np.sort, np.quantile, np.median
per bin, np.column_stack), on the compiled path and on the NumPy one, on varied data."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from calibration.decode import noise, ptc_select
from calibration.decode.noise import harmonic_leak, residual_line
from calibration.decode.ptc_fit import LinearVariance, binned_line, level_bins
from tests.calibration.decode import ptc_reference as ref


@pytest.fixture(params=["compiled", "numpy"])
def path(request, monkeypatch):
    """Run with the compiled passes (numba loaded) or force the NumPy path."""
    if request.param == "compiled":
        from calibration.decode import ptc_kernels  # (loads numba)

        kernels = ptc_kernels
        assert ptc_select.compiled() is kernels
    else:
        kernels = None
    monkeypatch.setattr(ptc_select, "compiled", lambda: kernels)
    monkeypatch.setattr(noise, "compiled", lambda: kernels)
    return request.param


def _sample(seed: int, n: int = 40000, kind: str = "ptc", sets: int = 6, leak: float = 3e-3):
    """A noise sample like the decoder's: levels (ties: means of 8-bit steps), dof of several
    values, rss with a photon-transfer variance, a display harmonic in `sets` sets' powers,
    clipped and unusable pixels."""
    rng = np.random.default_rng(seed)
    level = np.round(rng.uniform(0, 250, n) * 6) / 6
    if kind == "dark":  # most pixels at the dark level (a fisheye's surround)
        level[rng.random(n) < 0.8] = 1.5
    if kind == "two_levels":
        level = np.where(rng.random(n) < 0.5, 3.0, 200.0)
    if kind == "negative":  # float frames, black subtracted: levels around and below zero
        level = rng.normal(2.0, 4.0, n)
    dof = rng.choice([6.0, 12.0, 30.0, 37.0, 44.0], n)
    dof[rng.random(n) < 0.05] = 3.0  # clipped steps leave fewer
    var = 0.3 + 0.02 * np.maximum(level, 0)
    rss = dof * var * rng.chisquare(dof) / dof
    power = rng.uniform(0, 400, (sets, n)) * (rng.random((sets, 1)) < 0.8)
    rss = rss + leak * power.sum(axis=0)
    rss[rng.random(n) < 0.01] = 0.0  # constant readings
    rss[rng.random(n) < 0.002] = 80 * var[:1]  # model errors
    level[rng.random(n) < 0.001] = np.nan
    rss[rng.random(n) < 0.001] = np.nan
    dof[rng.random(n) < 0.001] = 0.0
    f32 = (level, rss, dof, np.asfortranarray(power))
    return tuple(a.astype(np.float32) for a in f32)


CASES = [(1, "ptc", 6, 3e-3), (2, "ptc", 6, 0.0), (3, "dark", 4, 2e-3), (4, "two_levels", 6, 3e-3),
         (5, "negative", 2, 5e-3), (6, "ptc", 6, 1e-2), (7, "dark", 6, 0.0)]


@pytest.mark.parametrize(("seed", "kind", "sets", "leak"), CASES)
def test_residual_line_matches_the_plain_code(path, seed, kind, sets, leak):
    level, rss, dof, power = _sample(seed, kind=kind, sets=sets, leak=leak)
    for floor in (1.0 / 12.0, 1e-12):
        dark = level[: level.size // 3]
        got = residual_line(level, rss, dof, power, floor, dark)
        want = ref.residual_line(level, rss, dof, power, floor, dark)
        assert got == want  # the same floats and the same leak list (or None)
    if seed == 1:
        assert got[1] is not None  # (the harmonic path ran)


def test_residual_line_with_few_or_flat_pixels(path):
    rng = np.random.default_rng(9)
    level, rss, dof, power = _sample(11, n=3000)
    for n in (10, 70, 900, 3000):  # under 64 usable, few bins, under 1000 pixels, enough
        args = (level[:n], rss[:n], dof[:n], power[:, :n], 1 / 12, level[:0])
        assert residual_line(*args) == ref.residual_line(*args)
    flat = np.full(3000, 7.0, np.float32)  # one level: one bin, no line
    args = (flat, rss, dof, power, 1 / 12, flat)
    assert residual_line(*args) == ref.residual_line(*args) == (None, None)
    dark = (rng.random(3000) < 0.9) * 1.0 + rng.uniform(0, 1e-3, 3000)
    args = (dark.astype(np.float32), rss, dof, power * 0, 1 / 12, flat)  # no harmonic at all
    assert residual_line(*args) == ref.residual_line(*args)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_level_bins_and_line_match(path, dtype):
    level, rss, dof, _ = (a.astype(dtype) for a in _sample(21, n=30000))
    for max_pixels in (1 << 19, 4000):  # all usable pixels, an even subsample
        got = level_bins(level, rss, dof, max_pixels=max_pixels)
        want = ref.level_bins(level, rss, dof, max_pixels=max_pixels)
        assert got.bins == want.bins and np.array_equal(got.x, want.x)
        assert np.array_equal(got.order, want.order) and np.array_equal(got.m, want.m)
        assert np.array_equal(got.ordered, want.ordered)
        assert binned_line(got, rss, dof, 1 / 12, 2.0) == ref.binned_line(want, rss, dof,
                                                                          1 / 12, 2.0)
        # fewer usable pixels (the harmonic removed): from the previous bins, no new sort
        less = np.where(np.arange(rss.size) % 97 == 5, 0, rss).astype(dtype)
        again = level_bins(level, less, dof, max_pixels=max_pixels, previous=got)
        plain = ref.level_bins(level, less, dof, max_pixels=max_pixels)
        assert again.bins == plain.bins and np.array_equal(again.x, plain.x)
        assert np.array_equal(again.ordered, plain.ordered)
        assert np.array_equal(again.order, plain.order)
        assert level_bins(level, rss, dof, max_pixels=max_pixels, previous=got) is got


def test_sorted_quantiles_are_numpys():
    rng = np.random.default_rng(4)
    q = np.linspace(0.0, 1.0, 17)
    for n in (1, 2, 3, 16, 17, 64, 1000, 4097):
        for values in (rng.normal(0, 50, n), rng.integers(0, 4, n) * 0.5, np.full(n, -2.5)):
            for dtype in (np.float32, np.float64):
                ordered = np.sort(values.astype(dtype))
                got, want = ptc_select.sorted_quantiles(ordered, q), np.quantile(ordered, q)
                assert got.dtype == want.dtype and np.array_equal(got, want)


def test_sorted_without_is_a_fresh_sort():
    rng = np.random.default_rng(5)
    values = (rng.integers(1, 50, 5000) / 3).astype(np.float32)
    ordered = np.sort(values)
    drop = rng.choice(values.size, 300, replace=False)
    removed = values[drop]
    assert np.array_equal(ptc_select.sorted_without(ordered, removed),
                          np.sort(np.delete(values, drop)))
    zeros = np.sort(np.concatenate([values, np.array([-0.0, 0.0], np.float32)]))
    assert ptc_select.sorted_without(zeros, removed) is None  # (a fresh sort decides)


def _medians_cases(rng):
    yield rng.normal(1, 0.3, 20000)  # one bracketed bin
    yield np.sort(rng.normal(1, 0.3, 20000))  # sorted: the strided sample is exact
    yield np.sort(rng.normal(1, 0.3, 20001))[::-1].copy()
    yield np.tile(np.arange(50.0), 400)  # a sawtooth the stride may alias
    yield np.full(9000, 0.7)  # all equal
    yield np.where(rng.random(30000) < 0.6, 1.25, rng.uniform(0, 3, 30000))  # ties at the middle
    v = rng.exponential(1.0, 12000)
    v[777] = np.nan  # a NaN: the bin's median is NaN
    yield v
    yield np.concatenate([rng.uniform(0, 1, 5000), [np.inf, np.inf, -np.inf]])
    yield rng.integers(0, 3, 17).astype(np.float64)  # a small bin


def test_bin_medians_are_numpys(path):
    rng = np.random.default_rng(6)
    for values in _medians_cases(rng):
        n = values.size
        cuts = sorted({0, n, *rng.integers(0, n, 3).tolist()})
        bins = [slice(a, b) for a, b in itertools.pairwise(cuts) if b - a >= 1]
        bins.append(slice(0, n))
        got = ptc_select.bin_medians(values, bins)
        want = np.array([float(np.median(values[b])) for b in bins])
        assert np.array_equal(got, want, equal_nan=True)
        m = rng.uniform(0, 250, n).astype(np.float32)  # over a line at each level
        for line in (LinearVariance(0.3, 0.02, 1 / 12), LinearVariance(-1.0, 0.01, 0.0)):
            with np.errstate(divide="ignore", invalid="ignore"):  # (a line at 0: inf, NaN)
                got = ptc_select.bin_medians(values, bins, line, m)
                rel = values / line.variance(m)
            want = np.array([float(np.median(rel[b])) for b in bins])
            assert np.array_equal(got, want, equal_nan=True)


def test_bin_ratios_and_group_by_level_are_numpys(path):
    level, rss, dof, _ = _sample(31, n=20000)
    good = np.flatnonzero(np.isfinite(level) & np.isfinite(rss) & (dof >= 1) & (rss > 0))
    order = np.random.default_rng(1).permutation(good.size)
    want = ref.variance_ratio(rss[good], np.rint(dof[good]).astype(np.int64))[order]
    assert np.array_equal(ptc_select.bin_ratios(rss, dof, good, order), want)
    m = level[good]
    inner = np.unique(np.quantile(m, np.linspace(0, 1, 17)))[1:-1]
    which = np.clip(np.searchsorted(np.r_[-np.inf, inner], m, side="right") - 1, 0, None)
    got_order, bounds, ordered = ptc_select.group_by_level(m, inner, m.min(), m.max())
    assert np.array_equal(got_order, np.argsort(which, kind="stable"))
    assert np.array_equal(bounds, np.searchsorted(np.sort(which), np.arange(inner.size + 2)))
    assert np.array_equal(ordered, m[got_order])


@pytest.mark.filterwarnings("ignore:Mean of empty slice", "ignore:invalid value")
def test_harmonic_leak_matches_the_plain_code(path):
    level, rss, dof, power = _sample(41, n=50000, leak=4e-3)
    first = LinearVariance(0.3, 0.02, 1 / 12)
    for rows in (1 << 16, 5000):
        got = harmonic_leak(rss, dof, level, power, first, max_rows=rows)
        assert got is not None
        assert np.array_equal(got, ref.harmonic_leak(rss, dof, level, power, first, rows))
    sparse = np.where(np.arange(power.shape[1]) % 10 == 3, power, 0).astype(np.float32)
    assert harmonic_leak(rss, dof, level, sparse, first, 5000) is None  # (rows seen: no power)
    assert ref.harmonic_leak(rss, dof, level, sparse, first, 5000) is None
    power[2, 100] = np.nan  # a NaN column is not used
    for line in (first, LinearVariance(-0.5, 0.0, 0.0), LinearVariance(1e6, 0.0, 1.0)):
        got = harmonic_leak(rss, dof, level, power, line)
        want = ref.harmonic_leak(rss, dof, level, power, line)
        assert (got is None and want is None) or np.array_equal(got, want)


@pytest.mark.parametrize("levels", ["tied", "continuous"])
def test_bins_after_the_harmonic_match_a_fresh_start(path, levels):
    """Bins rebuilt from the previous ones (fewer usable pixels): the same edges keep each
    pixel's bin (tied levels), other edges regroup; both as a fresh start would."""
    rng = np.random.default_rng(8)
    n = 50000
    level = (rng.integers(10, 30, n) * 0.5 if levels == "tied" else rng.uniform(0, 250, n))
    level, rss, dof = (a.astype(np.float32) for a in (level, rng.uniform(0.1, 9, n),
                                                      rng.choice([6.0, 14.0], n)))
    first = level_bins(level, rss, dof)
    less = np.where(rng.random(n) < 0.003, 0, rss).astype(np.float32)
    got, want = level_bins(level, less, dof, previous=first), ref.level_bins(level, less, dof)
    assert np.array_equal(got.edges[1:-1], first.edges[1:-1]) == (levels == "tied")
    for name in ("usable", "good", "order", "x", "count", "m", "ordered", "edges", "bounds"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    assert got.bins == want.bins
    assert binned_line(got, less, dof, 1 / 12, None) == ref.binned_line(want, less, dof,
                                                                        1 / 12, None)


def test_group_by_level_with_close_edges_and_levels_outside(path):
    """Several edges in one table bucket, levels outside the given range, NaN, inf: each
    level still counts exactly the edges at or below it."""
    rng = np.random.default_rng(12)
    m = np.round(rng.uniform(0, 100, 20000), 1).astype(np.float32)
    m[:4] = [np.nan, np.inf, -5.0, 1e30]
    inner = np.array([-1.0, 10.0, 10.0 + 1e-9, 10.05, 10.1, 50.0, 50.0 + 1e-12, 99.9, 200.0])
    which = np.zeros(m.shape, np.int16)
    for edge in inner:
        which += m >= edge
    for lo, hi in ((0.0, 100.0), (20.0, 60.0), (7.0, 7.0)):
        order, bounds, ordered = ptc_select.group_by_level(m, inner, lo, hi)
        assert np.array_equal(order, np.argsort(which, kind="stable"))
        assert np.array_equal(bounds, np.searchsorted(np.sort(which), np.arange(inner.size + 2)))
        assert np.array_equal(ordered, m[order], equal_nan=True)
