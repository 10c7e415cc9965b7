"""`decode_stack` over a whole stack with the compiled kernels: observed (progress or
cancellation between groups of ranges) or not (every range in one parallel pass), the
maps are the same to the bit."""

from __future__ import annotations

import numpy as np

from acquisition.patterns import build_plan
from calibration.decode import DecodeOptions, decode_stack
from tests.calibration.decode.test_decode import render

KEYS = ("x", "y", "sigma_x", "sigma_y", "mask", "modulation_x", "modulation_y", "blur_x",
        "blur_y")


def test_unobserved_decode_equals_observed_one(monkeypatch):
    import calibration.decode.decoder as decoder_module
    from calibration.decode.kernel_warm import warm_up

    warm_up()
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)
    plan = build_plan(1920, 1080, 0.2745)
    stack, _, _ = render(plan, white=320.0, blur=1.5, seed=5)  # some steps clipped
    options = DecodeOptions(chunk_pixels=1024)  # many ranges: several groups
    seen: list[int] = []
    for noise in (None, 1.5):
        seen.clear()
        observed = decode_stack(plan, stack, noise=noise, options=options,
                                progress=lambda done, total, stage: seen.append(done),
                                prepare=True)
        assert seen[-1] == len(plan.frames) and len(set(seen)) > 3  # groups reported
        quiet = decode_stack(plan, stack, noise=noise, options=options, prepare=True)
        cancel = decode_stack(plan, stack, noise=noise, options=options, prepare=True,
                              cancelled=lambda: False)
        assert quiet.meta == observed.meta == cancel.meta
        for key in KEYS:
            for got in (quiet, cancel):
                np.testing.assert_array_equal(getattr(got, key), getattr(observed, key),
                                              err_msg=key)
