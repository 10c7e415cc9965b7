"""Glue between the accumulator and the compiled accumulation kernel; pixel-range views.

`add_compiled` folds a batch of frames into the full-image sums (threads over column
ranges). `ChunkSums` is what finishing a range of pixels reads: views of the full-image
sums (`chunk_view`) or, when a whole stack is at hand, sums accumulated for that range
only (`StackPass`: no full-image state, each frame byte read once).
"""

from __future__ import annotations

import functools
import math
import os
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.decode.accumulate import DecodeError, FrameAccumulator, SetSums
from calibration.decode.accumulate_kernel import (
    BLOCK,
    KIND_BRIGHT,
    KIND_COSINE,
    KIND_DARK,
    KIND_SKIP,
    NO_CLIP_HI,
    NO_CLIP_LO,
    accumulate_block,
)

_KINDS = {"bright": KIND_BRIGHT, "dark": KIND_DARK, "cos": KIND_COSINE}


@functools.lru_cache(maxsize=1)
def pool() -> ThreadPoolExecutor:
    """One thread per core (at most 4), shared by the compiled decoder stages."""
    return ThreadPoolExecutor(min(os.cpu_count() or 1, 4), thread_name_prefix="decode")


# a forked child has none of the parent's threads: it starts its own pool
os.register_at_fork(after_in_child=pool.cache_clear)


def in_parallel(fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[Any]:
    """`fn`'s results over `items` from the shared pool, in the items' order as they come
    (the caller acts on the first ones while the pool works on the rest)."""
    if len(items) <= 1:
        return map(fn, items)
    return pool().map(fn, items)


def run_parallel(fn: Callable[[Any], None], items: Sequence[Any]) -> None:
    """Run `fn` over `items` in the shared pool (the kernels release the GIL)."""
    for _ in in_parallel(fn, items):
        pass


def _roles(acc: FrameAccumulator, indices: Sequence[int]) -> tuple[np.ndarray, ...]:
    """(kind, set, step) int64 arrays of the batch's plan indices."""
    roles = [acc.roles.get(i, ("skip", 0, 0)) for i in indices]
    kind = np.array([_KINDS.get(r[0], KIND_SKIP) for r in roles], dtype=np.int64)
    return kind, np.array([r[1] for r in roles], dtype=np.int64), np.array(
        [r[2] for r in roles], dtype=np.int64)


def _pieces(n: int, count: int) -> list[tuple[int, int]]:
    """`count` column ranges over n columns, aligned to the kernel's cache block."""
    step = max(BLOCK, -(-n // count // BLOCK) * BLOCK)
    return [(c, min(step, n - c)) for c in range(0, n, step)]


def clip_thresholds(acc: FrameAccumulator) -> tuple[float, float]:
    """Clip thresholds as float32 values that classify every float32 sample like the
    float64 ones (`v <= low`, `v >= high`): the largest float32 <= low, the smallest >= high."""
    lo = NO_CLIP_LO if acc.low is None else float(acc.low)
    hi = NO_CLIP_HI if acc.high is None else float(acc.high)
    lo32, hi32 = np.float32(lo), np.float32(hi)
    if lo32 > lo:
        lo32 = np.nextafter(lo32, np.float32(-np.inf))
    if hi32 < hi:
        hi32 = np.nextafter(hi32, np.float32(np.inf))
    return float(lo32), float(hi32)


def _note(acc: FrameAccumulator, kind: np.ndarray, fset: np.ndarray, top: float) -> None:
    """Frame counts and the brightest sample after a batch."""
    acc.n_bright += int((kind == KIND_BRIGHT).sum())
    acc.n_dark += int((kind == KIND_DARK).sum())
    for k in fset[kind == KIND_COSINE].tolist():
        acc.sets[k].seen += 1
    if (acc.high is not None or acc.low is not None) and (kind == KIND_COSINE).any():
        acc.max_seen = max(acc.max_seen, top)


def add_frames(acc: FrameAccumulator, indices: Sequence[int], stack: Any,
               rows: Sequence[int] | None = None) -> None:
    """Fold several frames at once with the compiled kernel: `stack[rows[j]]` (default
    `stack[j]`) is plan frame `indices[j]`; `stack` is an (F, H, W) array (e.g. a
    memory-mapped frame store) or a sequence of 2-D frames. Each frame is read once, in
    cache blocks."""
    indices = [int(i) for i in indices]
    rows = list(range(len(indices))) if rows is None else [int(r) for r in rows]
    if len(rows) != len(indices):
        raise DecodeError(f"frames: {len(indices)} indices for {len(rows)} frames")
    if len(set(indices)) != len(indices):
        raise DecodeError("frames: a plan index given twice in one batch")
    if not isinstance(stack, np.ndarray) or stack.ndim != 3:
        for index, row in zip(indices, rows, strict=True):
            img = acc.accept(index, stack[row])
            add_compiled(acc, [index], np.ascontiguousarray(img).reshape(1, -1), [0])
        return
    for index, row in zip(indices, rows, strict=True):
        acc.check(index, stack[row])
    flat = stack.reshape(stack.shape[0], -1)
    if not flat.flags.c_contiguous:
        flat, rows = np.ascontiguousarray(flat[rows]), list(range(len(rows)))
    for index in indices:
        acc.accept(index, stack[rows[0]])  # (checked above)
    add_compiled(acc, indices, flat, rows)


def add_compiled(acc: FrameAccumulator, indices: Sequence[int], flat: np.ndarray,
                 rows: Sequence[int]) -> None:
    """Fold frames `flat[rows[j]]` (plan frames `indices[j]`, (F, H*W) C-contiguous) into
    the full-image sums of `acc`, in parallel over column ranges."""
    lay = acc.kernel_layout
    kind, fset, fstep = _roles(acc, indices)
    use = np.asarray(rows, dtype=np.int64)
    lo, hi = clip_thresholds(acc)
    npix = flat.shape[1]
    squares = (acc.squares.reshape(-1) if acc.squares is not None
               else np.empty(0, acc.squares_dtype))
    if acc.bits is None:  # the OpenCV path ran before (no step clipped so far)
        acc.bits = np.zeros((len(acc.sets), npix), dtype=acc.bits_dtype)
    bright, dark = acc.bright.reshape(-1), acc.dark.reshape(-1)
    pieces = _pieces(npix, 4 * min(os.cpu_count() or 1, 4))
    tops = np.full((len(pieces), 1), -np.inf)
    clipped = np.zeros((len(pieces), len(acc.sets)), dtype=np.int64)

    def one(p: int) -> None:
        c0, n = pieces[p]
        accumulate_block(flat, use, kind, fset, fstep, lay.weights, lay.row0, lay.nrows, lo, hi,
                         c0, c0, n, acc.block, acc.bits, squares, bright, dark, tops[p],
                         clipped[p])

    run_parallel(one, range(len(pieces)))
    _note(acc, kind, fset, float(tops.max()))
    for k in np.flatnonzero(clipped.sum(axis=0)).tolist():
        acc.excluded_row(k)


@dataclass
class ChunkSums:
    """The sums of a range of pixels (1-D arrays over the range), as finishing reads them."""

    sets: list[SetSums]
    block: Any  # (rows, n) float32
    bits: Any | None  # (S, n) excluded-step bit masks, None when no step clipped
    squares: Any | None
    bright: Any  # flat sums
    dark: Any
    # the C-contiguous full-image arrays these are columns col0.. of (the kernels index
    # those: rows of 2-D views have unknown strides, which stops LLVM vectorizing)
    full: tuple[Any, ...] | None = None
    col0: int = 0

    @property
    def size(self) -> int:
        return int(self.bright.shape[0])

    def take(self, idx: Any) -> ChunkSums:
        """The sums of the pixels `idx` of this range (a gathered copy)."""
        def pick(x: Any) -> Any:
            return None if x is None else x[..., idx]

        bits, block = pick(self.bits), self.block[:, idx]
        clipped = [s.excluded is not None for s in self.sets]
        return ChunkSums(_views(self.sets, block, bits, clipped), block, bits,
                         pick(self.squares), self.bright[idx], self.dark[idx])


def _views(sets: list[SetSums], block: Any, bits: Any | None,
           clipped: Sequence[bool]) -> list[SetSums]:
    """SetSums whose arrays are rows of `block` (and of `bits` where the set clipped)."""
    out, r0 = [], 0
    for k, s in enumerate(sets):
        rows = [block[r0 + r] for r in range(s.rows)]
        excluded = bits[k] if bits is not None and clipped[k] else None
        out.append(SetSums(s.layout, rows[1], rows[2], rows[0], excluded, s.harmonics,
                           rows[3:], s.seen))
        r0 += s.rows
    return out


def chunk_view(acc: FrameAccumulator, sl: slice) -> ChunkSums:
    """Views of the full-image sums over the flattened pixel range `sl`."""
    block = acc.block[:, sl]
    bits = acc.bits[:, sl] if acc.bits is not None else None
    squares = acc.squares.reshape(-1)[sl] if acc.squares is not None else None
    clipped = [s.excluded is not None for s in acc.sets]
    full = (acc.block, acc.bits, None if acc.squares is None else acc.squares.reshape(-1),
            acc.bright.reshape(-1), acc.dark.reshape(-1))
    return ChunkSums(_views(acc.sets, block, bits, clipped), block, bits, squares,
                     acc.bright.reshape(-1)[sl], acc.dark.reshape(-1)[sl], full, sl.start)


_LOCAL = threading.local()


def _buffers(acc: FrameAccumulator, n: int) -> tuple[np.ndarray, ...]:
    """This thread's reusable range buffers (sums, bits, squares, bright, dark), zeroed."""
    need = (acc.rows, len(acc.sets), n, acc.bits_dtype, acc.need_squares, acc.squares_dtype)
    bufs = getattr(_LOCAL, "bufs", None)
    if bufs is None or bufs[0] != need:
        sq = np.empty(n if acc.need_squares else 0, dtype=acc.squares_dtype)
        bufs = (need, np.empty((acc.rows, n), np.float32),
                np.empty((len(acc.sets), n), acc.bits_dtype), sq, np.empty(n), np.empty(n))
        _LOCAL.bufs = bufs
    for arr in bufs[1:]:
        arr.fill(0)
    return bufs[1:]


class StackPass:
    """The accumulation of a whole stack in plan order, range by range (`finish_stack`):
    no full-image sums, each frame byte read once. The frame counts, known from the plan,
    are recorded in the accumulator at the start (finishing needs them), its brightest
    cosine sample at the end (`done`)."""

    def __init__(self, acc: FrameAccumulator, flat: np.ndarray) -> None:
        self.acc = acc
        self.flat = flat  # (F, H*W) C-contiguous, frame i = plan frame i
        count = len(acc.plan.frames)
        self.roles = _roles(acc, range(count))
        self.use = np.arange(count, dtype=np.int64)
        self.top = -math.inf  # brightest cosine sample summed so far, by all threads
        self.lock = threading.Lock()
        kind, fset, _ = self.roles
        _note(acc, kind, fset, -math.inf)
        acc.added[:] = True  # (summed range by range, each frame byte once)

    def sums(self, sl: slice) -> ChunkSums:
        """Sums of the pixel range `sl`, in this thread's buffers (valid until its next
        call); any thread of the pool may call it."""
        acc, c0, n = self.acc, sl.start, sl.stop - sl.start
        lay = acc.kernel_layout
        kind, fset, fstep = self.roles
        block, bits, squares, bright, dark = _buffers(acc, n)
        top = np.full(1, -np.inf)
        clipped = np.zeros(len(acc.sets), dtype=np.int64)
        lo, hi = clip_thresholds(acc)
        accumulate_block(self.flat, self.use, kind, fset, fstep, lay.weights, lay.row0,
                         lay.nrows, lo, hi, c0, 0, n, block, bits, squares, bright, dark, top,
                         clipped)
        with self.lock:
            self.top = max(self.top, float(top[0]))
        bits = bits if clipped.any() else None
        return ChunkSums(_views(acc.sets, block, bits, (clipped > 0).tolist()), block, bits,
                         squares if acc.need_squares else None, bright, dark)

    def done(self) -> None:
        """Record the pass's brightest cosine sample in the accumulator (every range summed)."""
        acc = self.acc
        if acc.high is not None or acc.low is not None:
            acc.max_seen = max(acc.max_seen, self.top)
