"""Hiding invalid pixels range by range (`hide_invalid`, then `hide_screen_edges`) gives the
maps, mask and counts of marking the screen edges on the whole image first and hiding after."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.decode.validity import (
    HIDDEN,
    REASONS,
    hide_invalid,
    hide_screen_edges,
    mark_screen_edges,
)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_range_by_range_hiding_equals_hiding_the_whole_image_after_the_edges(seed):
    rng = np.random.default_rng(seed)
    h, w = 37, 53
    # a screen (valid codes and a few rule failures) inside a dark surround (no_screen)
    reason = rng.choice(np.array([0, 0, 0, 0, 4, 5], dtype=np.uint8), size=(h, w))
    yy, xx = np.mgrid[:h, :w]
    reason[(yy - 18) ** 2 / 14**2 + (xx - 26) ** 2 / 20**2 > 1] = REASONS.index("no_screen")
    out = {key: rng.normal(size=h * w) for key in (*HIDDEN, "modulation_x", "modulation_y")}
    # what the decoder did before: the whole image's edges, then mask and NaN in one pass
    want_reason = reason.copy()
    mark_screen_edges(want_reason)
    want_mask = want_reason.reshape(-1) == 0
    want = {key: np.where(want_mask | key.startswith("modulation"), v, np.nan)
            for key, v in out.items()}
    flat, mask = reason.reshape(-1).copy(), np.empty(h * w, dtype=bool)
    tallies = [hide_invalid(out, mask, flat, slice(s, min(s + 500, h * w)))
               for s in range(0, h * w, 500)]
    counts = hide_screen_edges(flat.reshape(h, w), mask, out, tallies)
    assert np.array_equal(flat, want_reason.reshape(-1))
    assert np.array_equal(mask, want_mask)
    for key in out:
        assert np.array_equal(out[key], want[key], equal_nan=True), key
    tally = np.bincount(want_reason.reshape(-1), minlength=len(REASONS))
    assert counts == {name: int(tally[code]) for code, name in enumerate(REASONS)}
    assert counts["screen_edge"] > 0 and counts["valid"] > 0
