"""Compiled, cache-blocked accumulation (numba): many frames into the running sums at once.

For a block of a few hundred pixels it loops over every frame of the batch, so each
frame's bytes are read once and the block's sums stay in the L1/L2 cache (the per-frame
OpenCV path re-reads and re-writes every full-image sum for every frame: tens of bytes of
memory traffic per pixel-frame, against ~1 here). Same sums as accumulate.py: per set
`s0, a, b` and the extra harmonics (rows of one float32 block), clipped samples zeroed
with their step's bit set, `sum v^2` and the flats in their own arrays.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from calibration.decode.kernel_cache import drop_stale_kernels

BLOCK = 512  # pixels per cache block: rows x BLOCK x 4 bytes stays in L2

NO_CLIP_LO, NO_CLIP_HI = -3.0e38, 3.0e38
KIND_SKIP, KIND_BRIGHT, KIND_DARK, KIND_COSINE = 0, 1, 2, 3


# no NaN/inf assumptions (float32 frames may hold them), no FMA contraction: the sums
# round like the OpenCV path (acc + round(w v)), so both give the same maps
@njit(cache=True, error_model="numpy", nogil=True, fastmath={"reassoc", "nsz", "arcp"})
def accumulate_block(
    frames,  # (F_all, N) C-contiguous frames (uint8, uint16 or float32), columns = pixels
    use,  # (B,) rows of `frames` in this batch
    kind, fset, fstep,  # (B,) role of each batch frame: KIND_*, set index, phase step
    weights,  # (S, R, T) float32 weight of step t in row r of set s (row 0: 1 for s0)
    row0, nrows,  # (S,) first row of each set in `sums`, and its number of rows
    lo, hi,  # float32 values: clipped when v <= lo or v >= hi (NO_CLIP_LO / NO_CLIP_HI: never)
    fcol, ocol, n,  # frames columns fcol..fcol+n go to output columns ocol..ocol+n
    sums,  # (M, N_out) float32 running sums (added to)
    bits,  # (S, N_out) unsigned per-pixel bit mask of excluded steps (or-ed into)
    squares,  # (N_out,) float32/float64 sum v^2 (added to; size 0 when not kept)
    bright, dark,  # (N_out,) float64 flat sums (added to)
    vmax,  # (1,) float64: raised to the largest cosine sample seen
    clipped,  # (S,) int64: incremented by the clipped samples seen per set
) -> None:
    """Add the batch's frames to the sums over one column range."""
    buf = np.empty(BLOCK, dtype=np.float32)
    lo32, hi32 = np.float32(lo), np.float32(hi)
    need_sq = squares.shape[0] > 0
    top = vmax[0]
    for j0 in range(0, n, BLOCK):
        m = min(BLOCK, n - j0)
        fc = fcol + j0
        oc = ocol + j0
        # Inner loops index sliced views from 0 (no negative-index wraparound: vectorized).
        for f in range(use.shape[0]):
            row = frames[use[f], fc:fc + m]
            kd = kind[f]
            if kd == KIND_BRIGHT or kd == KIND_DARK:
                flat = bright[oc:oc + m] if kd == KIND_BRIGHT else dark[oc:oc + m]
                for j in range(m):
                    flat[j] += row[j]
                continue
            if kd != KIND_COSINE:
                continue
            k = fset[f]
            count = 0
            for j in range(m):  # branch-free
                x = np.float32(row[j])
                clip = (x <= lo32) | (x >= hi32)
                buf[j] = np.float32(0.0) if clip else x
                count += clip
            peak = row[0]
            for j in range(1, m):  # in the frame's own dtype (an integer max)
                v = row[j]
                peak = v if v > peak else peak
            top = max(top, float(peak))
            if count:
                clipped[k] += count
                mask = bits[k, oc:oc + m]
                bit = 1 << fstep[f]
                for j in range(m):  # branch-free (vectorized): a third of 8-bit pixels clip
                    x = np.float32(row[j])
                    mask[j] |= bit if (x <= lo32) | (x >= hi32) else 0
            if need_sq:
                sq = squares[oc:oc + m]
                if squares.itemsize == 4:  # float32 sums of uint8 squares: exact integers
                    for j in range(m):
                        sq[j] += buf[j] * buf[j]
                else:
                    for j in range(m):  # float64 products: uint16 squares exceed float32
                        xd = np.float64(buf[j])
                        sq[j] += xd * xd
            r0 = row0[k]
            for r in range(nrows[k]):
                w = weights[k, r, fstep[f]]
                if w == 0.0:
                    continue
                dst = sums[r0 + r, oc:oc + m]
                for j in range(m):
                    dst[j] += w * buf[j]
    vmax[0] = top


drop_stale_kernels(globals())  # before any kernel runs: no machine code from older sources
