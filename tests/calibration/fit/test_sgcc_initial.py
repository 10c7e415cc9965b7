"""sgcc/initial.py helpers."""

from __future__ import annotations

import numpy as np

from calibration.fit.sgcc.initial import _unique_rows


def test_unique_rows_equals_numpy_unique_along_rows():
    rng = np.random.default_rng(0)
    for _ in range(5):
        pix = rng.integers(0, 40, (5000, 2)).astype(np.float64)
        pix[::7] += 0.5  # not only integer pixels
        assert np.array_equal(_unique_rows(pix), np.unique(pix, axis=0))
