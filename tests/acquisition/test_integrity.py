"""Integrity check of large frames: compared on a regular grid, same verdicts."""

from __future__ import annotations

import numpy as np

from acquisition.integrity import MAX_COMPARED, compare_references


def _scene(rng: np.random.Generator, shift_px: float = 0.0, dark_dn: float = 10.0):
    """(white, dark, fine cosine) 8-bit frames of a 1024x1280 camera with 1 DN noise."""
    h, w = 1024, 1280
    x = np.arange(w)[None, :] + shift_px
    white = np.full((h, w), 200.0)
    cosine = 105 + 95 * np.cos(2 * np.pi * x / 12.0) * np.ones((h, 1))
    frames = [white, np.full((h, w), dark_dn), cosine]
    return tuple(np.clip(np.rint(f + rng.normal(0, 1.0, (h, w))), 0, 255).astype(np.uint8)
                 for f in frames)


def test_large_frames_are_compared_on_a_grid_with_the_same_verdicts() -> None:
    rng = np.random.default_rng(3)
    first = _scene(rng)
    steady = compare_references(first, _scene(rng))
    assert steady.ok, steady.reasons
    assert steady.metrics["grid_step"] == 3  # 1.3 Mpixel > MAX_COMPARED
    assert steady.metrics["lit_pixels"] <= MAX_COMPARED
    assert 0.8 < steady.metrics["noise_white_dn"] < 1.2  # the noise is still measured right
    moved = compare_references(first, _scene(rng, shift_px=1.0))
    assert not moved.ok and "motion" in moved.reason
    lit = compare_references(first, _scene(rng, dark_dn=14.0))
    assert not lit.ok and "ambient light" in lit.reason


def test_small_frames_use_every_pixel() -> None:
    rng = np.random.default_rng(4)
    a = tuple(f[:200, :300] for f in _scene(rng))
    b = tuple(f[:200, :300] for f in _scene(rng))
    report = compare_references(a, b)
    assert report.ok and report.metrics["grid_step"] == 1
    assert report.metrics["lit_pixels"] == 200 * 300
