"""Compiled finish straight from the running sums (numba), per block of pixels.

The per-set cosine fits (phase.py `fit_set`: closed form, or least squares over the kept
steps of pixels with clipped steps, kernel_clipped.py), the noise variances (decoder
`_noise_variances`: a given linear noise model, or the photon-transfer line with the
per-pixel model-error test, `use_step_levels` where steps clipped), the flat contrast,
then the sigmas, phases and blur (kernel_sets.py) and the unwrapping (kernel_unwrap.py)
in one pass, without (S, n) staging arrays. Without pattern tables (plans of > 16 steps),
pixels with some steps clipped are left to the array path: `reason` 255 marks them.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.decode.kernel import P_MIN_CONTRAST
from calibration.decode.kernel_cache import drop_stale_kernels
from calibration.decode.kernel_clipped import fit_block
from calibration.decode.kernel_sets import (
    MODE_GIVEN,
    MODE_LINE,
    MODE_OWN,
    N_FLOOR,
    N_MODE,
    blur_fit,
    contrast,
    explained,
    general_set_block,
    line_of,
    line_var,
    nyquist,
    set_block,
)
from calibration.decode.kernel_unwrap import STATE_ROWS, unwrap_block

DIRTY = 255  # reason code of pixels this kernel leaves to the array path

# Pixels per block: the block's scratch (~170 KB with 6 period sets) stays in a core's L2
# (256 KB and up on common CPUs), and the per-block costs (array views, the unwrapping
# call, loop set-up) come a quarter as often as at 128, where they were 15-25 % of the
# kernel's time (benchmarks/finish_kernel.py; the maps are identical at any block size).
BLOCK = 512


# no fastmath: NaN and infinity tests matter here
@njit(cache=True, error_model="numpy", nogil=True)
def finish_sums(
    sums, bits, squares, bright, dark,  # (M, N), (S, N), (N,) or (0,), (N,), (N,)
    c0,  # first column of the range in the inputs (C-contiguous: vectorized loops)
    row0, nrows, steps,  # (S,) int64 set layout in `sums`
    noise,  # (7,) see kernel_sets.N_* indices
    lin,  # (3,) the noise line as c0 + slope * level above a threshold (kernel_clipped)
    leak,  # (S,) r^2 of the display harmonic N/2 in each set's residual (residual mode)
    flats,  # (2,) number of bright and dark flats
    tail,  # (D + 1,) chi2.isf(1e-6, d) / d by residual dof d (residual mode)
    set_axis, periods, amps, chi2_limit, extents, params,  # as kernel.finish_pixels
    pos_out, sig_out, mod_out, blur_out, o0,  # (2, N_out) outputs from column o0
    reason,  # (n,) uint8 reason codes of the range
    tables,  # (index, rows, basis, widths): `kernel_clipped.PatternTables.kernel_tables`;
    # empty index: none (`kernel_clipped.no_tables`)
) -> None:
    """Decode the pixels of a range from their sums: those with every step kept, those
    with every step clipped (no fit: `no_screen` or `clipped`) and, with `tables`, those
    with some steps clipped; without tables these get reason DIRTY.

    Per block of pixels, everything per set (fits, variances, sigmas, wrapped phases, the
    blur line sums) runs in loops over the block's pixels that LLVM vectorizes (blocks
    with clipped pixels: their fits first, kernel_clipped.fit_block); then the unwrapping
    and the validity rules (kernel_unwrap.py, vectorized the same way)."""
    n_sets = row0.shape[0]
    n = reason.shape[0]
    mode = int(noise[N_MODE])
    residual = mode != MODE_GIVEN
    floor = noise[N_FLOOR]
    dof = 0
    for k in range(n_sets):
        dof += steps[k] - nrows[k]
    excess_limit = tail[dof] if mode == MODE_LINE else np.inf
    line = line_of(noise)
    f64 = np.float64
    have_tables = tables[0].shape[0] > 0
    dirty = np.empty(BLOCK, dtype=np.bool_)
    dead = np.empty(BLOCK, dtype=np.bool_)
    skip = np.empty(BLOCK, dtype=np.bool_)
    own = np.empty(BLOCK)
    excess = np.empty(BLOCK, dtype=np.bool_)
    expl = np.empty(BLOCK)
    wrapped = np.empty((n_sets, BLOCK))
    sig = np.empty((n_sets, BLOCK))
    use = np.empty((n_sets, BLOCK), dtype=np.bool_)
    blur = np.empty((6, 2, BLOCK))  # per axis: sw, sx, sy, sxx, sxy, count
    snr_a = np.empty((3, 2, BLOCK))  # per axis: anchor SNR, finest modulation, anchor fitted
    snr = np.empty(BLOCK)
    lg, lg_e, lg_m, wt = np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK)
    state = np.empty((STATE_ROWS, BLOCK))
    # per-pixel fits of blocks with clipped pixels (kernel_clipped.fit_block)
    fits = np.empty((3, n_sets, BLOCK), dtype=np.float32)
    fitted = np.empty((n_sets, BLOCK), dtype=np.bool_)
    partial = np.empty((n_sets, BLOCK), dtype=np.bool_)
    covs = np.empty((6, n_sets, BLOCK))
    rdof, rlev, low = np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK, dtype=np.bool_)
    scratch = np.empty((3, BLOCK))
    p = np.empty(tables[2].shape[2])
    first, last = np.full(2, -1), np.full(2, -1)
    for k in range(n_sets):
        if first[set_axis[k]] < 0:
            first[set_axis[k]] = k
        last[set_axis[k]] = k
    nb, nd = flats[0], flats[1]
    floor_sigma = np.sqrt(floor * (1.0 / nb + 1.0 / nd))
    for b0 in range(0, n, BLOCK):
        m = min(BLOCK, n - b0)
        j0 = c0 + b0  # input column of the block
        d, dd = dirty[:m], dead[:m]
        d[:] = False
        dd[:] = bits.shape[0] == n_sets
        for k in range(bits.shape[0]):
            bk, every = bits[k, j0:j0 + m], (1 << steps[k]) - 1
            for j in range(m):
                d[j] |= bk[j] != 0
                dd[j] &= bk[j] == every
        general = clean = False
        for j in range(m):
            clean |= d[j]
        clean = not clean  # (no clipped step: the dark-block shortcut may apply)
        if have_tables:
            for j in range(m):
                general |= d[j] and not dd[j]
        ow, ex = own[:m], excess[:m]
        ex[:] = mode == MODE_OWN
        blur[:, :, :m] = 0.0
        if general:  # some pixels with clipped steps: per-pixel fits first
            lit_row, unlit_row = bright[j0:j0 + m], dark[j0:j0 + m]
            for j in range(m):
                lit, unlit = lit_row[j] / nb, unlit_row[j] / nd
                skip[j] = not (lit - unlit) >= params[P_MIN_CONTRAST] * floor_sigma
                d[j] = False
            fit_block(sums, bits, squares, j0, m, row0, nrows, steps, tables, skip, residual,
                      False, mode != MODE_OWN, lin, line, leak, fits, fitted, covs, partial,
                      ow, rdof, rlev, low, scratch, p)
            if residual:
                for j in range(m):
                    own_j = max(max(ow[j], 0.0) / max(rdof[j], 1.0), floor)
                    ow[j] = own_j if rdof[j] > 0 else np.nan
            if mode == MODE_LINE:
                mean0 = fits[2, 0]
                for j in range(m):
                    level = max(f64(mean0[j]), 0.0)
                    ex[j] = ow[j] > line_var(line, level) * tail[int(rdof[j])]
            for k in range(n_sets):
                ax = set_axis[k]
                general_set_block(fits[0, k], fits[1, k], fits[2, k], fitted[k], covs[:, k],
                                  partial[k], sums, row0[k], nrows[k], steps[k], periods[k],
                                  amps[k], line, params, j0, m, ow, ex, wrapped[k], sig[k],
                                  use[k], blur[:, ax], snr_a[:, ax], k == first[ax], lg, lg_e,
                                  lg_m, wt)
        else:
            if mode != MODE_OWN:  # (the flats' noise is the line's: no residuals needed)
                contrast(bright, dark, flats, line, False, j0, m, ow, snr)
                if clean and _unlit(snr, m, params[P_MIN_CONTRAST]):
                    _dark_block(sums, row0, steps, last, j0, m, pos_out, sig_out, mod_out,
                                blur_out, o0 + b0, reason, b0)
                    continue
            if residual:  # residual variance per pixel (decoder `_residuals`)
                sq = squares[j0:j0 + m]
                for j in range(m):
                    ow[j] = f64(sq[j])
                for k in range(n_sets):
                    explained(sums, row0[k], nrows[k], steps[k], j0, m, expl)
                    for j in range(m):
                        ow[j] -= expl[j]
                    if leak[k] != 0.0:  # the display harmonic in the residual is not noise
                        nyquist(sums, row0[k], steps[k], j0, m, expl)
                        for j in range(m):
                            ow[j] -= leak[k] * expl[j]
                for j in range(m):
                    ow[j] = max(max(ow[j], 0.0) / max(dof, 1), floor)
            if mode == MODE_OWN:  # the flats' noise: each pixel's own residual variance
                contrast(bright, dark, flats, line, True, j0, m, ow, snr)
                if clean and _unlit(snr, m, params[P_MIN_CONTRAST]):
                    _dark_block(sums, row0, steps, last, j0, m, pos_out, sig_out, mod_out,
                                blur_out, o0 + b0, reason, b0)
                    continue
            if mode == MODE_LINE:
                s00 = sums[row0[0], j0:j0 + m]
                inv0 = np.float32(1.0 / steps[0])
                for j in range(m):
                    ex[j] = ow[j] > line_var(line, max(f64(s00[j] * inv0), 0.0)) * excess_limit
            for k in range(n_sets):
                ax = set_axis[k]
                set_block(sums, row0[k], nrows[k], steps[k], periods[k], amps[k], line,
                          params, j0, m, ow, ex, wrapped[k], sig[k], use[k], blur[:, ax],
                          snr_a[:, ax], k == first[ax], lg, lg_e, lg_m, wt)
        if general:
            contrast(bright, dark, flats, line, mode == MODE_OWN, j0, m, ow, snr)
        for ax in range(2):
            blur_fit(blur[:, ax], m)
        unwrap_block(m, wrapped, sig, use, blur, snr_a, snr, d, first, set_axis, periods,
                     chi2_limit, extents, params, pos_out, sig_out, mod_out, blur_out,
                     o0 + b0, reason[b0:b0 + m], state)
        codes = reason[b0:b0 + m]
        for j in range(m):  # every step clipped in every set: no fit (phase.fit_set)
            if dd[j]:
                q = 0.0 if mode == MODE_OWN else snr[j]  # (no residual dof: no noise level)
                codes[j] = 1 if not q >= params[P_MIN_CONTRAST] else 2
                for ax in range(2):
                    if first[ax] >= 0:
                        mod_out[ax, o0 + b0 + j] = 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _unlit(snr, m, min_contrast) -> bool:
    """Whether no pixel of the block passes the flat-contrast test (all `no_screen`)."""
    lit = False
    for j in range(m):
        lit |= snr[j] >= min_contrast
    return not lit


@njit(cache=True, error_model="numpy", nogil=True)
def _dark_block(sums, row0, steps, last, j0, m, pos_out, sig_out, mod_out, blur_out, o0,
                reason, b0) -> None:
    """A block of unclipped pixels that all see no screen (code 1 is final whatever the
    other rules say): what the full pass writes into the maps (as dark_chunks.py for a whole
    range): reason 1, each axis's modulation of its last set (`set_block`'s arithmetic),
    NaN positions, sigmas and blur (the decoder's mask hides them anyway)."""
    f32 = np.float32
    for ax in range(2):
        k = last[ax]
        if k < 0:
            continue  # the plan has no frames on this axis
        r0, scale = row0[k], f32(2.0 / steps[k])
        sa, sb = sums[r0 + 1, j0:j0 + m], sums[r0 + 2, j0:j0 + m]  # (views: loops vectorize)
        mod, pos = mod_out[ax, o0:o0 + m], pos_out[ax, o0:o0 + m]
        sig, blur = sig_out[ax, o0:o0 + m], blur_out[ax, o0:o0 + m]
        for j in range(m):
            a, b = float(sa[j] * scale), float(sb[j] * scale)
            mod[j] = math.sqrt(a * a + b * b)
            pos[j] = np.nan
            sig[j] = np.nan
            blur[j] = np.nan
    reason[b0:b0 + m] = 1


@njit(cache=True, error_model="numpy", nogil=True)
def residual_stats(sums, bits, squares, c0, row0, nrows, steps, level_out, rss_out, dof_out,
                   dirty_out, power_out, low_out, bright, dark, clip, leak, tables) -> None:
    """Residual-mode first pass (decoder `_residuals`) for the pixels of columns c0..:
    dof-weighted level, residual sum of squares, residual dof, each set's Nyquist power;
    `dirty_out` marks the pixels with clipped steps. With `tables` (non-empty index) those
    are fitted here too (kernel_clipped.py; `clip`: floor, bright and dark flat counts,
    min_contrast_snr, lazy span) and `low_out` marks a step clipped at the dark end, except
    those whose flat contrast is at least the lazy span: deferred (dof -1, no fit); without
    tables, they are left to the array path (`low_out` untouched)."""
    n = level_out.shape[0]
    n_sets = row0.shape[0]
    expl, own, lev = np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK)
    have_tables = tables[0].shape[0] > 0
    skip, low = np.empty(BLOCK, dtype=np.bool_), np.empty(BLOCK, dtype=np.bool_)
    fits = np.empty((3, n_sets, BLOCK), dtype=np.float32)
    fitted = np.empty((n_sets, BLOCK), dtype=np.bool_)
    partial = np.empty((n_sets, BLOCK), dtype=np.bool_)
    covs = np.empty((6, n_sets, BLOCK))
    rdof, scratch = np.empty(BLOCK), np.empty((3, BLOCK))
    p = np.empty(tables[2].shape[2])
    none, lin = (0.0, 0.0, 0.0, False, 0.0), np.zeros(3)  # (no noise line: no covariance)
    nb, nd = clip[1], clip[2]
    floor_sigma = np.sqrt(clip[0] * (1.0 / nb + 1.0 / nd))
    dof = 0.0
    for k in range(n_sets):
        dof += np.float32(steps[k] - nrows[k])
    for b0 in range(0, n, BLOCK):
        m = min(BLOCK, n - b0)
        j0 = c0 + b0
        d = dirty_out[b0:b0 + m]
        d[:] = False
        for k in range(bits.shape[0]):
            bk = bits[k, j0:j0 + m]
            for j in range(m):
                d[j] |= bk[j] != 0
        general = deferred = False
        if have_tables:
            for j in range(m):
                if d[j] and bright[j0 + j] / nb - dark[j0 + j] / nd >= clip[4]:
                    deferred = True
                else:
                    general |= d[j]
        if general:
            for j in range(m):
                lit, unlit = bright[j0 + j] / nb, dark[j0 + j] / nd
                skip[j] = not (lit - unlit) >= clip[3] * floor_sigma
            fit_block(sums, bits, squares, j0, m, row0, nrows, steps, tables, skip, True, True,
                      False, lin, none, leak, fits, fitted, covs, partial, own, rdof, lev,
                      low, scratch, p)
            for j in range(m):
                rss_out[b0 + j] = max(own[j], 0.0)
                level_out[b0 + j] = lev[j] / max(rdof[j], 1.0)
                dof_out[b0 + j] = rdof[j]
                low_out[b0 + j] = low[j]
            for k in range(n_sets):
                nyquist(sums, row0[k], steps[k], j0, m, expl)
                for j in range(m):
                    power_out[k, b0 + j] = 0.0 if bits[k, j0 + j] != 0 else expl[j]
            continue
        for j in range(m):
            own[j] = float(squares[j0 + j])
            lev[j] = 0.0
        for k in range(n_sets):
            explained(sums, row0[k], nrows[k], steps[k], j0, m, expl)
            dof_k = np.float32(steps[k] - nrows[k])
            s0 = sums[row0[k], j0:j0 + m]
            inv_n = np.float32(1.0 / steps[k])
            for j in range(m):
                own[j] -= expl[j]
                lev[j] += dof_k * (s0[j] * inv_n)
            nyquist(sums, row0[k], steps[k], j0, m, expl)
            power_out[k, b0:b0 + m] = expl[:m]
        for j in range(m):
            rss_out[b0 + j] = max(own[j], 0.0)
            level_out[b0 + j] = lev[j] / max(dof, 1.0)
            dof_out[b0 + j] = -1.0 if deferred and d[j] else dof
            low_out[b0 + j] = False


drop_stale_kernels(globals())  # before any kernel runs: no machine code from older sources
