"""Hiding invalid pixels range by range (`hide_invalid`, then the screen edges as rows become
final, `FinalRows`) gives the maps, mask and counts of marking the screen edges on the whole
image first and hiding after; rows it reports final do not change again."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.decode.validity import (
    EDGE_BAND_ROWS,
    HIDDEN,
    REASONS,
    FinalRows,
    hide_invalid,
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
    final = FinalRows(flat.reshape(h, w), mask, out)
    final.decoded(h * w)
    counts = final.counts(tallies)
    assert np.array_equal(flat, want_reason.reshape(-1))
    assert np.array_equal(mask, want_mask)
    for key in out:
        assert np.array_equal(out[key], want[key], equal_nan=True), key
    tally = np.bincount(want_reason.reshape(-1), minlength=len(REASONS))
    assert counts == {name: int(tally[code]) for code, name in enumerate(REASONS)}
    assert counts["screen_edge"] > 0 and counts["valid"] > 0


def _edges_by_definition(reason):
    """Valid pixels with a no_screen pixel among their 3x3 neighbours (the image's border
    pixels repeated outside it): nine shifted views of the whole image."""
    sees = np.pad(reason != REASONS.index("no_screen"), 1, mode="edge")
    h, w = reason.shape
    interior = np.ones((h, w), dtype=bool)
    for dv in range(3):
        for du in range(3):
            interior &= sees[dv:dv + h, du:du + w]
    return np.flatnonzero((reason == 0) & ~interior)


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (9, 1), (EDGE_BAND_ROWS, 7),
                                   (EDGE_BAND_ROWS + 1, 5), (2 * EDGE_BAND_ROWS + 3, 11)])
def test_screen_edges_band_by_band_are_the_3x3_neighbourhood_of_no_screen(shape):
    rng = np.random.default_rng(sum(shape))
    for fraction in (0.002, 0.05, 0.5):  # lone dark pixels (some at band edges) to dark areas
        reason = rng.choice(np.array([0, 0, 5], dtype=np.uint8), size=shape)
        reason[rng.random(shape) < fraction] = REASONS.index("no_screen")
        want = _edges_by_definition(reason)
        got_reason = reason.copy()
        edge = mark_screen_edges(got_reason)
        assert np.array_equal(np.sort(edge), want)
        expected = reason.reshape(-1).copy()
        expected[want] = REASONS.index("screen_edge")
        assert np.array_equal(got_reason.reshape(-1), expected)


def test_an_image_that_sees_the_screen_everywhere_has_no_screen_edge():
    reason = np.zeros((EDGE_BAND_ROWS + 2, 6), dtype=np.uint8)
    reason[3, 2] = REASONS.index("off_screen")
    flat, mask = reason.reshape(-1).copy(), np.empty(reason.size, dtype=bool)
    out = {key: np.ones(reason.size) for key in HIDDEN}
    tallies = [hide_invalid(out, mask, flat, slice(0, reason.size))]
    final = FinalRows(flat.reshape(reason.shape), mask, out)
    final.decoded(reason.size)
    counts = final.counts(tallies)
    assert counts["screen_edge"] == 0 and counts["off_screen"] == 1
    assert counts["valid"] == reason.size - 1 == int(mask.sum())
    assert np.array_equal(flat, reason.reshape(-1))


@pytest.mark.parametrize("step", [97, 1000, 4099])
def test_rows_reported_final_do_not_change_again(step):
    """Ranges decoded in pixel order: each `on_final(rows)` comes once rows [0, rows) hold
    their final codes, mask and maps (a resident maps buffer writes them to disk then), the
    rows a band at least apart, the last call every row."""
    rng = np.random.default_rng(step)
    h, w = 3 * EDGE_BAND_ROWS + 5, 41
    reason = rng.choice(np.array([0, 0, 0, 5], dtype=np.uint8), size=(h, w))
    reason[:, :6] = REASONS.index("no_screen")  # a dark surround down the whole left side
    reason[rng.random((h, w)) < 0.05] = REASONS.index("no_screen")
    out = {key: rng.normal(size=h * w) for key in HIDDEN}
    codes = reason.reshape(-1)
    want = reason.copy()  # the whole image's edges
    mark_screen_edges(want)
    want = want.reshape(-1)
    hidden = want != 0
    want_out = {key: np.where(hidden, np.nan, v) for key, v in out.items()}
    flat, mask = np.zeros(h * w, dtype=np.uint8), np.empty(h * w, dtype=bool)  # as decoded
    seen: list[tuple[int, np.ndarray, np.ndarray, dict]] = []

    def on_final(rows: int) -> None:
        n = rows * w
        seen.append((rows, flat[:n].copy(), mask[:n].copy(),
                     {key: v[:n].copy() for key, v in out.items()}))

    final = FinalRows(flat.reshape(h, w), mask, out, on_final)
    tallies = []
    for s in range(0, h * w, step):
        sl = slice(s, min(s + step, h * w))
        flat[sl] = codes[sl]  # (the range's codes appear when it is decoded)
        tallies.append(hide_invalid(out, mask, flat, sl))
        final.decoded(sl.stop)
    rows = [r for r, *_ in seen]
    assert rows[-1] == h and len(rows) >= 2
    assert (np.diff(rows[:-1]) >= EDGE_BAND_ROWS).all()  # (the last: the image's end)
    for r, kept_codes, kept_mask, kept in seen:
        n = r * w
        assert np.array_equal(kept_codes, want[:n]) and np.array_equal(kept_mask, ~hidden[:n])
        for key in out:
            assert np.array_equal(kept[key], want_out[key][:n], equal_nan=True), (r, key)
    assert final.counts(tallies)["screen_edge"] == int(np.count_nonzero(
        flat == REASONS.index("screen_edge"))) > 0
