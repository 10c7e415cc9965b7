"""Pixel ranges of a dark surround skip the compiled per-pixel pass with identical maps."""

from __future__ import annotations

import numpy as np

import calibration.decode.decoder as decoder_module
from acquisition.patterns import build_plan
from calibration.decode import DecodeOptions, StreamingDecoder
from calibration.decode.kernel_warm import warm_up
from tests.calibration.decode.test_decode import H, W, render

KEYS = ("x", "y", "sigma_x", "sigma_y", "mask", "modulation_x", "modulation_y", "blur_x",
        "blur_y")


def _decode(plan, stack, noise):
    dec = StreamingDecoder(plan, (H, W), noise=noise, options=DecodeOptions(chunk_pixels=64))
    dec.prepare()
    dec.add_frames(list(range(stack.shape[0])), stack)
    return dec.finish()


def test_dark_surround_ranges_skip_the_kernel_with_identical_maps(monkeypatch) -> None:
    warm_up()
    plan = build_plan(1920, 1080, 0.2745)
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)  # the compiled path
    stack, _, _ = render(plan, x0=-600.0, read=0.5, seed=4)  # ~95 columns left of the screen
    calls: list[bool] = []
    real = StreamingDecoder._finish_dark_range

    def counted(*args):
        calls.append(real(*args))
        return calls[-1]

    for noise in (None, 1.5):  # a given noise may be under the floor: never skipped
        calls.clear()
        monkeypatch.setattr(StreamingDecoder, "_finish_dark_range", counted)
        skipped = _decode(plan, stack, noise)
        dark = sum(calls)
        monkeypatch.setattr(StreamingDecoder, "_finish_dark_range", lambda *args: False)
        kernel = _decode(plan, stack, noise)
        if noise is None:  # most of [0, 64) of each row (10 DN, contrast noise 0.7 DN)
            assert dark > 0.8 * H, dark
        else:
            assert dark == 0
        assert skipped.valid_count() > 0.4 * H * W
        for key in KEYS:
            assert np.array_equal(getattr(skipped, key), getattr(kernel, key),
                                  equal_nan=key != "mask"), key
        assert skipped.meta["pixel_counts"] == kernel.meta["pixel_counts"]
