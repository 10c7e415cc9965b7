"""The noise sample's lazy first pass: pixels with clipped steps are fitted only when the
photon-transfer line needs them, and the maps equal those of a pass fitting them all."""

from __future__ import annotations

import pytest

import calibration.decode.decoder as decoder_module
import calibration.decode.finish as finish_module
from acquisition.patterns import build_plan
from calibration.decode import decode_stack
from calibration.decode.kernel_warm import warm_up
from tests.calibration.decode.test_decode import assert_same_maps, render


@pytest.mark.parametrize(("bright_from", "passes"), [(180, [True]), (0, [True, False])])
def test_lazy_noise_sample_equals_a_full_pass(monkeypatch, bright_from, passes) -> None:
    """Columns from `bright_from` on clip their brightest steps: with enough clean pixels
    one lazy pass suffices; with none (every pixel clipped) a second pass fits them all.
    Either way the line and the maps are those of an eager pass (every pixel fitted)."""
    warm_up()
    plan = build_plan(1920, 1080, 0.2745)
    stack, _, _ = render(plan, white=200.0, blur=1.5, seed=43)
    bright, _, _ = render(plan, white=320.0, blur=1.5, seed=43)
    stack[:, :, bright_from:] = bright[:, :, bright_from:]
    assert (stack[:, :, bright_from:] == 255).any(axis=0).mean() > 0.9
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)
    stats, seen = finish_module.residual_stats, []

    def eager(inputs, chunk, lazy=False):
        seen.append(lazy)
        return stats(inputs, chunk, False)

    monkeypatch.setattr(decoder_module, "residual_stats", eager)
    ref = decode_stack(plan, stack)
    assert seen and ref.meta["decoder"]["photon_transfer"] is not None
    seen.clear()

    def spy(inputs, chunk, lazy=False):
        seen.append(lazy)
        return stats(inputs, chunk, lazy)

    monkeypatch.setattr(decoder_module, "residual_stats", spy)
    got = decode_stack(plan, stack)
    assert sorted(set(seen), reverse=True) == passes
    assert_same_maps(got, ref)
