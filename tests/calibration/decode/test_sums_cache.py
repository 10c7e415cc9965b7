"""A long-lived worker's decoders reuse the previous pose's sums (`sums_cache`): zeroed
again, same maps; the kept memory is bounded (one decode's, dropped on another shape or
after a while)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from acquisition.patterns import build_plan
from calibration.decode import StreamingDecoder, sums_cache
from tests.calibration.decode.test_decode import H, W, render

KEYS = ("x", "y", "sigma_x", "sigma_y", "mask", "modulation_x", "modulation_y", "blur_x",
        "blur_y")


@pytest.fixture(autouse=True)
def empty_cache():
    sums_cache.release()
    yield
    sums_cache.release()


def _decode(plan, stack, shape=(H, W)):
    dec = StreamingDecoder(plan, shape)
    dec.prepare()
    block = dec._acc.block
    dec.add_frames(list(range(stack.shape[0])), stack)
    maps = dec.finish()
    dec.release()
    return maps, block


def test_next_decode_reuses_the_sums_zeroed_again_with_the_same_maps() -> None:
    plan = build_plan(1920, 1080, 0.2745)
    first, _, _ = render(plan, seed=1)
    second, _, _ = render(plan, seed=2, white=150.0)
    ref, _ = _decode(plan, second)  # a decoder with new sums
    sums_cache.release()
    _, block = _decode(plan, first)
    assert sums_cache.kept_bytes() >= block.nbytes
    got, reused = _decode(plan, second)
    assert reused is block  # the same memory, no new allocation
    for key in KEYS:
        assert np.array_equal(getattr(got, key), getattr(ref, key), equal_nan=key != "mask"), key
    assert got.meta["decoder"] == ref.meta["decoder"]


def test_kept_sums_are_dropped_for_another_shape_and_after_a_while(monkeypatch) -> None:
    plan = build_plan(1920, 1080, 0.2745)
    stack, _, _ = render(plan, seed=1)
    _, block = _decode(plan, stack)
    assert sums_cache.kept_bytes() > 0
    other = StreamingDecoder(plan, (H // 2, W))
    other.prepare()  # another camera: the kept arrays go, new ones are made
    assert other._acc.block is not block and sums_cache.kept_bytes() == 0
    monkeypatch.setattr(sums_cache, "KEEP_S", 0.05)
    other.release()
    assert sums_cache.kept_bytes() > 0
    time.sleep(0.5)
    assert sums_cache.kept_bytes() == 0
