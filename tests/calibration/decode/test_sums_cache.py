"""A long-lived worker's decoders reuse the previous pose's sums (`sums_cache`): zeroed
again, same maps; concurrent decodes of one size (a rig's cameras) each get a set; the kept
memory is bounded (at most `MAX_SETS` decodes', dropped on another shape or after a
while)."""

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


def _prepared(plan, count: int) -> list[StreamingDecoder]:
    decoders = [StreamingDecoder(plan, (H, W)) for _ in range(count)]
    for dec in decoders:
        dec.prepare()
    return decoders


def _set_bytes(dec: StreamingDecoder) -> int:
    acc = dec._acc
    return sum(a.nbytes for a in (acc.block, acc.bright, acc.dark, acc.squares)
               if a is not None)


def test_concurrent_decodes_of_one_size_each_reuse_a_kept_set() -> None:
    """A rig decoding three same-size cameras at once: at the next pose every camera's
    decoder gets sums kept from the last one, none allocates afresh."""
    plan = build_plan(1920, 1080, 0.2745)
    first = _prepared(plan, 3)
    blocks, size = {id(dec._acc.block) for dec in first}, _set_bytes(first[0])
    for dec in first:
        dec.release()
    assert sums_cache.kept_bytes() == 3 * size
    second = _prepared(plan, 3)
    assert {id(dec._acc.block) for dec in second} == blocks
    for dec in second:
        dec.release()
    assert sums_cache.kept_bytes() == 3 * size  # the sets taken from are not kept twice


def test_kept_sets_are_bounded(monkeypatch) -> None:
    monkeypatch.setattr(sums_cache, "MAX_SETS", 2)
    plan = build_plan(1920, 1080, 0.2745)
    decoders = _prepared(plan, 3)
    blocks, size = [dec._acc.block for dec in decoders], _set_bytes(decoders[0])
    for dec in decoders:
        dec.release()
    kept = {id(a) for a in sums_cache.kept_arrays()}
    assert id(blocks[0]) not in kept and {id(blocks[1]), id(blocks[2])} <= kept
    assert sums_cache.kept_bytes() == 2 * size
    single = _prepared(plan, 1)[0]  # one camera from now on
    assert single._acc.block is blocks[1]  # the oldest kept set first
    single.release()
    assert sums_cache.kept_bytes() == 2 * size
