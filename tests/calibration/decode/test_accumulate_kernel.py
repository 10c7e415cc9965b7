"""The compiled accumulation (accumulate_kernel.py) folds up to four frames of a set into
its sums per pass: the sums must equal, bit for bit, frame-by-frame float32 arithmetic
(acc + round(w v) in batch order, clipped samples zeroed, zero weights skipped), whatever
the batch order, dtype or non-finite samples."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.patterns import build_plan
from calibration.decode.accumulate import FrameAccumulator
from calibration.decode.batch import add_frames, clip_thresholds

SHAPE = (12, 70)  # 840 pixels: a full cache block and a partial one


def _frames(dtype: str, count: int, rng: np.random.Generator) -> np.ndarray:
    """Frames with clipped samples (0 and the top of integer dtypes; NaN, +-inf and values
    above the saturation level in float32 frames)."""
    if dtype == "float32":
        stack = rng.uniform(-5.0, 300.0, (count, *SHAPE)).astype(np.float32)
        flat = stack.reshape(count, -1)
        flat[:, 3] = np.nan
        flat[:, 5] = np.inf
        flat[::3, 7] = -np.inf
        return stack
    top = np.iinfo(dtype).max
    stack = rng.integers(0, top, (count, *SHAPE), endpoint=True).astype(dtype)
    stack.reshape(count, -1)[:, ::17] = top
    return stack


def _reference(acc: FrameAccumulator, order: list[int], stack: np.ndarray) -> tuple:
    """The sums frame by frame in NumPy float32 (float64 flats and uint16 squares)."""
    lay = acc.kernel_layout
    lo, hi = clip_thresholds(acc)
    block = np.zeros((acc.rows, stack[0].size), np.float32)
    bits = np.zeros((len(acc.sets), stack[0].size), acc.bits_dtype)
    squares = np.zeros(stack[0].size, acc.squares_dtype)
    flats = {"bright": np.zeros(stack[0].size), "dark": np.zeros(stack[0].size)}
    for i in order:
        kind, k, step = acc.roles.get(i, ("skip", 0, 0))
        if kind in flats:
            flats[kind] += stack[i].reshape(-1)
        if kind != "cos":
            continue
        v = stack[i].reshape(-1).astype(np.float32)
        clip = (v <= np.float32(lo)) | (v >= np.float32(hi))
        v[clip] = 0.0
        bits[k] |= (clip.astype(acc.bits_dtype) << step).astype(acc.bits_dtype)
        squares += v.astype(acc.squares_dtype) ** 2
        for r in range(lay.nrows[k]):
            w = lay.weights[k, r, step]
            if w != 0.0:
                row = block[lay.row0[k] + r]
                row[:] = row + w * v  # float32: the product rounded, then the sum
    return block, bits, squares, flats["bright"], flats["dark"]


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "float32"])
@pytest.mark.parametrize("residual", [True, False])  # 7 or 5 rows per set, squares or not
def test_grouped_accumulation_equals_frame_by_frame(dtype, residual):
    plan = build_plan(1920, 1080, 0.2745, steps=10)
    rng = np.random.default_rng(3)
    stack = _frames(dtype, len(plan.frames), rng)
    saturation = 250.0 if dtype == "float32" else None
    shuffled = rng.permutation(len(plan.frames)).tolist()  # sets interleaved
    for order in (list(range(len(plan.frames))), shuffled):
        acc = FrameAccumulator(plan, SHAPE, saturation_dn=saturation, need_squares=residual)
        acc.compiled = True
        half = len(order) // 2 + 1  # two batches, one group split between them
        for part in (order[:half], order[half:]):
            add_frames(acc, part, stack, rows=part)
        want = _reference(acc, order, stack)
        got = (acc.block, acc.bits, acc.squares.reshape(-1) if residual else want[2],
               acc.bright.reshape(-1), acc.dark.reshape(-1))
        for name, a, b in zip(("sums", "bits", "squares", "bright", "dark"), got, want,
                              strict=True):
            assert a.dtype == b.dtype, name
            np.testing.assert_array_equal(a, b, err_msg=name)
        cosine = [i for i in order if acc.roles.get(i, ("",))[0] == "cos"]
        assert acc.max_seen == float(np.nanmax(stack[cosine]))  # (no NaN first in a block)
