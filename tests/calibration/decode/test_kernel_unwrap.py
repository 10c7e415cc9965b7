"""The compiled block fusion of a finer period against the array path's `fuse_axis`, where
the neighbouring teeth weigh from nothing to enough to merge or make a pixel ambiguous."""

from __future__ import annotations

import numpy as np

from calibration.decode.kernel_unwrap import (
    S_AMB,
    S_CHI2,
    S_CODE,
    S_DOF,
    S_MU,
    S_VAR,
    STATE_ROWS,
    fuse_block,
)
from calibration.decode.unwrap import fuse_axis


def test_block_fusion_matches_the_array_path_at_every_tooth_weight():
    """Coarse sigmas from 0.05 to 150 px before a 384-px period: the teeth's log weight
    (half -+ tilt) spans ~1e-1 to ~3e7, across the vectorized path's cut-off."""
    rng = np.random.default_rng(3)
    period, extent, n = 384.0, 1920, 4096
    truth = rng.uniform(0.0, extent - 1.0, n)
    coarse_sigma = np.exp(rng.uniform(np.log(0.05), np.log(150.0), n))
    fine_sigma = np.full(n, 1.2)
    mu0 = truth + coarse_sigma * rng.standard_normal(n)
    c = np.mod(truth + fine_sigma * rng.standard_normal(n), period)
    half = 0.5 * period**2 / (coarse_sigma**2 + fine_sigma**2)
    assert (half < 69.0).sum() > 100 and ((half > 69.0) & (half < 740.0)).sum() > 100

    state = np.zeros((STATE_ROWS, n))
    state[S_MU], state[S_VAR], state[S_CODE] = mu0, coarse_sigma**2, 99.0
    fuse_block(n, c, fine_sigma, np.ones(n, dtype=np.bool_), period, state)

    # the array path from the same prior: a coarsest "period" far wider than the screen
    # puts every pixel's prior at mu0 with zero ambiguity
    wide = 1e7
    ref = fuse_axis(np, [mu0, c], [coarse_sigma, fine_sigma], [wide, period],
                    [np.ones(n, bool), np.ones(n, bool)], extent)
    np.testing.assert_allclose(state[S_MU], ref.position, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.sqrt(state[S_VAR]), ref.sigma, rtol=1e-12, atol=0)
    np.testing.assert_allclose(state[S_AMB], ref.ambiguity, rtol=1e-12, atol=1e-25)
    np.testing.assert_allclose(state[S_CHI2], ref.chi2, rtol=1e-12)
    assert np.all(state[S_DOF] == 1.0)
    merged_or_ambiguous = half < 69.0
    assert np.any(state[S_AMB][merged_or_ambiguous] > 1e-6)  # the scalar path did run
