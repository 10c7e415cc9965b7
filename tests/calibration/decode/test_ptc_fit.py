"""`ptc_fit.level_bins` (its bins by comparisons with the edges, its bin medians from the
sorted levels) gives exactly what the plain definition gives: bins by `searchsorted`,
medians by `np.median`, also with many tied levels (8-bit frames)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from calibration.decode.ptc_fit import level_bins, usable_pixels


def _by_definition(mean, rss, dof, bins=16):
    good = usable_pixels(mean, rss, dof)
    m = mean[good]
    edges = np.unique(np.quantile(m, np.linspace(0.0, 1.0, bins + 1)))
    which = np.clip(np.searchsorted(edges, m, side="right") - 1, 0, len(edges) - 2)
    order = np.argsort(which, kind="stable")
    bounds = np.searchsorted(which[order], np.arange(len(edges)))
    groups = [slice(int(lo), int(hi)) for lo, hi in itertools.pairwise(bounds) if hi - lo >= 16]
    return order, groups, np.array([float(np.median(m[order][b])) for b in groups])


@pytest.mark.parametrize("levels", ["uniform", "ties", "two_values", "skewed"])
def test_level_bins_match_their_definition(levels):
    rng = np.random.default_rng(7)
    n = 30000
    mean = {"uniform": rng.uniform(0, 255, n), "ties": rng.integers(0, 6, n) * 1.0,
            "two_values": np.where(rng.random(n) < 0.7, 7.0, 0.1 * rng.integers(0, 3, n)),
            "skewed": np.round(rng.exponential(20, n), 1)}[levels].astype(np.float32)
    rss = rng.uniform(0, 2, n).astype(np.float32)
    rss[rng.random(n) < 0.05] = 0  # (not usable)
    dof = np.full(n, 7.0, np.float32)
    got = level_bins(mean, rss, dof)
    order, groups, x = _by_definition(mean, rss, dof)
    if len(groups) < 4:
        assert got is None
        return
    assert got.bins == groups
    assert np.array_equal(got.order, order)
    assert np.array_equal(got.x, x)  # bit for bit
