"""Residual report helpers: the binned magnitude map."""

from __future__ import annotations

import numpy as np

from calibration.report import binned_rms


def test_binned_rms_is_the_rms_per_bin_and_blank_where_empty():
    # 8 points in a 4x2 image -> bins of sqrt(4*2*4/8) = 2 px: a 2x1 grid of bins.
    pix = np.array([[0.5, 0.5], [1.5, 1.5], [0.2, 1.9], [1.9, 0.1],
                    [2.5, 0.5], [3.5, 1.5], [2.1, 1.1], [3.9, 0.9]])
    mag = np.array([1.0, 1.0, 1.0, 1.0, 3.0, 4.0, 3.0, 4.0])
    np.testing.assert_allclose(binned_rms(pix, mag, 4, 2), [[1.0, np.sqrt(12.5)]])
    sparse = binned_rms(pix[:1], mag[:1], 40, 40)  # one point: one bin covers the image
    assert sparse.shape == (1, 1) and sparse[0, 0] == 1.0
    two = binned_rms(np.array([[0.5, 0.5], [39.5, 3.5]]), np.ones(2), 40, 4)  # 3 bins
    assert two.shape == (1, 3) and np.isnan(two[0, 1]) and two[0, 0] == two[0, 2] == 1.0
