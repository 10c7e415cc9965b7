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


GROUP = 4  # consecutive frames of one set folded into the sums in one pass


def accumulate_block(frames, use, kind, fset, fstep, weights, row0, nrows, lo, hi, fcol, ocol,
                     n, sums, bits, squares, bright, dark, vmax, clipped) -> None:
    """Add the batch's frames to the sums over one column range (arguments: `_accumulate`)."""
    scratch = [np.empty(BLOCK, dtype=np.float32) for _ in range(GROUP)]
    _accumulate(frames, use, kind, fset, fstep, weights, row0, nrows, lo, hi, fcol, ocol, n,
                sums, bits, squares, bright, dark, vmax, clipped, *scratch)


# no NaN/inf assumptions (float32 frames may hold them), no FMA contraction: the sums
# round like the OpenCV path (acc + round(w v), frame after frame), so both give the same maps
@njit(cache=True, error_model="numpy", nogil=True, fastmath={"nsz", "arcp"})
def _accumulate(
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
    buf0, buf1, buf2, buf3,  # (BLOCK,) float32 scratch: the samples of a group's frames
) -> None:
    """Add the batch's frames to the sums over one column range. Up to GROUP consecutive
    frames of one set are folded into each of its rows in one pass (one load and store of
    the row per group, not per frame), in batch order: the same additions in the same order
    as frame by frame. The scratch rows are arguments: LLVM vectorizes the group loops."""
    lo32, hi32 = np.float32(lo), np.float32(hi)
    need_sq = squares.shape[0] > 0
    top = vmax[0]
    for j0 in range(0, n, BLOCK):
        m = min(BLOCK, n - j0)
        fc = fcol + j0
        oc = ocol + j0
        f = 0
        while f < use.shape[0]:
            kd = kind[f]
            if kd == KIND_BRIGHT or kd == KIND_DARK:
                row = frames[use[f], fc:fc + m]
                flat = bright[oc:oc + m] if kd == KIND_BRIGHT else dark[oc:oc + m]
                for j in range(m):
                    flat[j] += row[j]
            if kd != KIND_COSINE:
                f += 1
                continue
            k = fset[f]
            g = 1  # the group: frames f..f+g of set k
            while g < GROUP and f + g < use.shape[0] and kind[f + g] == KIND_COSINE \
                    and fset[f + g] == k:
                g += 1
            for i in range(g):
                top = max(top, _samples(frames[use[f + i], fc:fc + m],
                                        buf0 if i == 0 else buf1 if i == 1 else
                                        buf2 if i == 2 else buf3,
                                        bits[k, oc:oc + m], 1 << fstep[f + i], lo32, hi32, m,
                                        clipped, k))
            if need_sq:
                sq = squares[oc:oc + m]
                if squares.itemsize == 4 and g == GROUP:  # exact integers for uint8 frames
                    for j in range(m):
                        a = sq[j] + buf0[j] * buf0[j]
                        a = a + buf1[j] * buf1[j]
                        a = a + buf2[j] * buf2[j]
                        sq[j] = a + buf3[j] * buf3[j]
                else:
                    for i in range(g):
                        b = buf0 if i == 0 else buf1 if i == 1 else buf2 if i == 2 else buf3
                        if squares.itemsize == 4:
                            for j in range(m):
                                sq[j] += b[j] * b[j]
                        else:  # float64 products: uint16 squares exceed float32
                            for j in range(m):
                                xd = np.float64(b[j])
                                sq[j] += xd * xd
            for r in range(nrows[k]):
                dst = sums[row0[k] + r, oc:oc + m]
                w0 = weights[k, r, fstep[f]]
                w1 = weights[k, r, fstep[f + 1]] if g > 1 else np.float32(0.0)
                w2 = weights[k, r, fstep[f + 2]] if g > 2 else np.float32(0.0)
                w3 = weights[k, r, fstep[f + 3]] if g > 3 else np.float32(0.0)
                if g == GROUP and w0 != 0.0 and w1 != 0.0 and w2 != 0.0 and w3 != 0.0:
                    for j in range(m):
                        a = dst[j] + w0 * buf0[j]
                        a = a + w1 * buf1[j]
                        a = a + w2 * buf2[j]
                        dst[j] = a + w3 * buf3[j]
                    continue
                for i in range(g):  # a zero weight adds nothing (not even 0 * inf)
                    w = w0 if i == 0 else w1 if i == 1 else w2 if i == 2 else w3
                    if w == 0.0:
                        continue
                    b = buf0 if i == 0 else buf1 if i == 1 else buf2 if i == 2 else buf3
                    for j in range(m):
                        dst[j] += w * b[j]
            f += g
    vmax[0] = top


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def _samples(row, out, mask, bit, lo32, hi32, m, clipped, k) -> float:
    """One frame's samples as float32 into `out`, the clipped ones zeroed, their step's bit
    set in `mask` and counted in clipped[k]; returns the frame's largest sample."""
    count = 0
    for j in range(m):  # branch-free
        x = np.float32(row[j])
        clip = (x <= lo32) | (x >= hi32)
        out[j] = np.float32(0.0) if clip else x
        count += clip
    peak = row[0]
    for j in range(1, m):  # in the frame's own dtype (an integer max)
        v = row[j]
        peak = v if v > peak else peak
    if count:
        clipped[k] += count
        for j in range(m):  # branch-free (vectorized): a third of 8-bit pixels clip
            x = np.float32(row[j])
            mask[j] |= bit if (x <= lo32) | (x >= hi32) else 0
    return float(peak)


drop_stale_kernels(globals())  # before any kernel runs: no machine code from older sources
