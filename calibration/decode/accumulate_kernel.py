"""Compiled one-pass sums of one period set's buffered frames (numba).

Summing frame by frame reads and writes every float32 sum once per frame (8 sums x 10
steps = 160 passes over 4-byte arrays per set); this kernel reads each pixel's steps once
and writes each sum once, so a set costs about one pass over its frames.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _sum_range(frames, weights, high, low, start, stop, sums, squares, excluded):
    """Sums over pixels [start, stop): rows of `sums` = s0, then sum v*weights[j] per row j.

    Samples >= high or <= low are clipped: left out of every sum and flagged in the
    per-pixel bit mask `excluded` (bit = step). Returns (any clipped, largest sample).
    """
    steps = frames.shape[0]
    n_w = weights.shape[0]
    acc = np.empty(n_w + 1)
    any_clip = False
    top = -np.inf
    for i in range(start, stop):
        acc[:] = 0.0
        sq = 0.0
        bits = 0
        for s in range(steps):
            v = float(frames[s, i])
            if v > top:
                top = v
            if v >= high or v <= low:
                bits |= 1 << s
                continue
            acc[0] += v
            sq += v * v
            for j in range(n_w):
                acc[j + 1] += v * weights[j, s]
        for j in range(n_w + 1):
            sums[j, i] = acc[j]
        if squares.shape[0]:
            squares[i] += sq
        if bits:
            any_clip = True
        excluded[i] = bits
    return any_clip, top


def sum_set(frames: np.ndarray, weights: np.ndarray, high: float, low: float,
            sums: np.ndarray, squares: np.ndarray, excluded: np.ndarray) -> tuple[bool, float]:
    """Fill `sums` (1 + W, n) from `frames` (steps, n) on threads over pixel ranges."""
    n = frames.shape[1]
    workers = max(1, min(os.cpu_count() or 1, 4, n // (1 << 16)))
    bounds = np.linspace(0, n, workers + 1).astype(np.int64)

    def part(k: int) -> tuple[bool, float]:
        return _sum_range(frames, weights, high, low, bounds[k], bounds[k + 1], sums, squares,
                          excluded)

    if workers == 1:
        results = [part(0)]
    else:
        with ThreadPoolExecutor(workers) as pool:
            results = list(pool.map(part, range(workers)))
    return any(r[0] for r in results), max(r[1] for r in results)
