"""Blocks of pixels that all see no screen take the compiled finish's shortcut
(kernel_sums `_dark_block`) with the maps of the full per-pixel pass."""

from __future__ import annotations

import numpy as np
import pytest

import calibration.decode.decoder as decoder_module
from acquisition.patterns import build_plan
from calibration.decode import DecodeOptions, StreamingDecoder
from calibration.decode.kernel_warm import warm_up
from calibration.decode.ptc_fit import LinearVariance
from calibration.shared.plan import FlatFrame
from tests.calibration.decode.test_decode import H, W, render

KEYS = ("x", "y", "sigma_x", "sigma_y", "mask", "modulation_x", "modulation_y", "blur_x",
        "blur_y")
DARK_ROW = 120  # rows from here on see no screen (whole blocks of the kernel)
LIT_COL = 7  # ... except this column from row DARK_ROW + 3 in the second stack


def _decode(plan, stack, noise):
    # ranges that do not start at a block boundary: short blocks at each range's end
    dec = StreamingDecoder(plan, (H, W), noise=noise, options=DecodeOptions(chunk_pixels=5000))
    dec.prepare()
    dec.add_frames(list(range(stack.shape[0])), stack)
    return dec.finish()


@pytest.mark.parametrize("mode", ["given", "line", "own"])
def test_dark_blocks_give_the_full_pass_maps(monkeypatch, mode) -> None:
    """One stack with whole dark blocks, one with a pixel of each of those blocks given a
    flat contrast (it passes the contrast test, fails a later rule): the full pass runs
    there for every pixel of the block. The other pixels' maps are the same, bit for bit,
    with a given noise, a photon-transfer line and each pixel's own residual variance."""
    warm_up()
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)  # the compiled path
    # a fixed noise line (or none: own residuals), not one fitted to each stack's pixels
    line = {"line": (LinearVariance(2.0, 0.02, 0.3), None), "own": (None, None)}.get(mode)
    if line is not None:
        monkeypatch.setattr(decoder_module, "residual_line", lambda *args, **kw: line)
    plan = build_plan(1920, 1080, 0.2745)
    stack, _, _ = render(plan, seed=5)
    rng = np.random.default_rng(6)
    dark = rng.normal(10.0, 1.5, (stack.shape[0], H - DARK_ROW, W))
    stack[:, DARK_ROW:] = np.clip(np.rint(dark), 0, 255).astype(np.uint8)
    stack[:, DARK_ROW - 1, 100:] = stack[:, DARK_ROW, 100:]  # a partly dark row
    lit = stack.copy()
    for i, frame in enumerate(plan.frames):
        if isinstance(frame, FlatFrame):
            lit[i, DARK_ROW + 3:, LIT_COL] = 200 if frame.level > 0.5 else 10
    noise = 1.5 if mode == "given" else None
    skipped, full = _decode(plan, stack, noise), _decode(plan, lit, noise)
    counts = skipped.meta["pixel_counts"]
    assert counts["no_screen"] >= (H - DARK_ROW) * W
    assert counts["valid"] > 0.3 * H * W
    changed = H - DARK_ROW - 3
    assert full.meta["pixel_counts"]["no_screen"] == counts["no_screen"] - changed
    keep = np.ones((H, W), dtype=bool)
    keep[DARK_ROW + 3:, LIT_COL] = False
    for key in KEYS:
        got, ref = getattr(skipped, key), getattr(full, key)
        assert np.array_equal(got[keep], ref[keep], equal_nan=key != "mask"), key
    assert np.isfinite(skipped.modulation_x[DARK_ROW:]).all()
