"""Compiled per-pixel finish straight from the running sums (numba), for unclipped pixels.

The per-set cosine fits (phase.py `fit_set` with all steps kept: closed form), the noise
variances (decoder `_noise_variances`: a given linear noise model, or the photon-transfer
line with the per-pixel model-error test), the flat contrast and then `decode_pixel`
(kernel.py) in one pass, without (S, n) staging arrays. Pixels with any clipped step
(`bits` nonzero) are left to the array path: `reason` 255 marks them.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.decode.kernel import P_MIN_CONTRAST, P_PERIOD_SNR
from calibration.decode.kernel_cache import drop_stale_kernels
from calibration.decode.kernel_clipped import clipped_block, clipped_residuals
from calibration.decode.kernel_unwrap import STATE_ROWS, unwrap_block
from calibration.decode.vecmath import atan2_f32, log_inplace

_TWO_PI = 2.0 * math.pi
DIRTY = 255  # reason code of pixels this kernel leaves to the array path

# Indices of `noise`: the noise mode and the linear variance model's coefficients.
N_MODE, N_OFFSET, N_SLOPE, N_BLACK, N_CLAMP, N_FLOOR, N_LINE_FLOOR = range(7)
MODE_GIVEN, MODE_LINE, MODE_OWN = 0, 1, 2  # given model / photon-transfer line / own residual


@njit(cache=True, error_model="numpy", inline="always")
def _line(line, level: float) -> float:
    """Variance of the linear noise model `line` (`_line_of`) at `level`: offset + slope *
    (level - black)+, at least the line's floor (a photon-transfer line: quantization)."""
    offset, slope, black, clamp, floor = line
    x = level - black
    x = 0.0 if clamp and not x > 0.0 else x
    return max(offset + slope * x, floor)


@njit(cache=True, error_model="numpy", inline="always")
def _line_of(noise):
    """The linear model of `noise` as scalars (offset, slope, black, clamp, floor): loops
    that read them from the array reload them per pixel (possible aliasing) and stay scalar."""
    return (noise[N_OFFSET], noise[N_SLOPE], noise[N_BLACK], noise[N_CLAMP] != 0.0,
            noise[N_LINE_FLOOR])


BLOCK = 128  # pixels per block: the per-set scratch rows stay in L1


# no fastmath: NaN and infinity tests matter here
@njit(cache=True, error_model="numpy", nogil=True)
def finish_sums(
    sums, bits, squares, bright, dark,  # (M, N), (S, N), (N,) or (0,), (N,), (N,)
    c0,  # first column of the range in the inputs (C-contiguous: vectorized loops)
    row0, nrows, steps,  # (S,) int64 set layout in `sums`
    noise,  # (7,) see N_* indices
    leak,  # (S,) r^2 of the display harmonic N/2 in each set's residual (residual mode)
    flats,  # (2,) number of bright and dark flats
    tail,  # (D + 1,) chi2.isf(1e-6, d) / d by residual dof d (residual mode)
    set_axis, periods, amps, chi2_limit, extents, params,  # as kernel.finish_pixels
    pos_out, sig_out, mod_out, blur_out, o0,  # (2, N_out) outputs from column o0
    reason,  # (n,) uint8 reason codes of the range
    tables,  # kernel_clipped.PatternTables (index, rows, basis); empty index: none
) -> None:
    """Decode the pixels of a range from their sums: those with every step kept, those
    with every step clipped (no fit: `no_screen` or `clipped`) and, with `tables`, those
    with some steps clipped (kernel_clipped.py); others get reason DIRTY.

    Per block of pixels, everything per set (fits, variances, sigmas, wrapped phases, the
    blur line sums) runs in loops over the block's pixels that LLVM vectorizes; then the
    unwrapping and the validity rules (kernel_unwrap.py, vectorized the same way)."""
    n_sets = row0.shape[0]
    n = reason.shape[0]
    mode = int(noise[N_MODE])
    residual = mode != MODE_GIVEN
    dof = 0
    for k in range(n_sets):
        dof += steps[k] - nrows[k]
    excess_limit = tail[dof] if mode == MODE_LINE else np.inf
    line = _line_of(noise)
    f64 = np.float64
    dirty = np.empty(BLOCK, dtype=np.bool_)
    dead = np.empty(BLOCK, dtype=np.bool_)
    own = np.empty(BLOCK)
    excess = np.empty(BLOCK, dtype=np.bool_)
    expl = np.empty(BLOCK)
    wrapped = np.empty((n_sets, BLOCK))
    sig = np.empty((n_sets, BLOCK))
    use = np.empty((n_sets, BLOCK), dtype=np.bool_)
    blur = np.empty((6, 2, BLOCK))  # per axis: sw, sx, sy, sxx, sxy, count
    snr_a = np.empty((2, 2, BLOCK))  # per axis: anchor SNR, last (finest) modulation
    snr = np.empty(BLOCK)
    lg, lg_e, lg_m, wt = np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK)
    state = np.empty((STATE_ROWS, BLOCK))
    first = np.full(2, -1)
    for k in range(n_sets):
        if first[set_axis[k]] < 0:
            first[set_axis[k]] = k
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
        # residual variance per pixel (decoder `_residuals`)
        ow = own[:m]
        if residual:
            for j in range(m):
                ow[j] = f64(squares[j0 + j])
            for k in range(n_sets):
                _explained(sums, row0[k], nrows[k], steps[k], j0, m, expl)
                for j in range(m):
                    ow[j] -= expl[j]
                if leak[k] != 0.0:  # the display harmonic in the residual is not noise
                    _nyquist(sums, row0[k], steps[k], j0, m, expl)
                    for j in range(m):
                        ow[j] -= leak[k] * expl[j]
            floor = noise[N_FLOOR]
            for j in range(m):
                ow[j] = max(max(ow[j], 0.0) / max(dof, 1), floor)
        ex = excess[:m]
        ex[:] = mode == MODE_OWN
        if mode == MODE_LINE:
            s00 = sums[row0[0], j0:j0 + m]
            inv0 = np.float32(1.0 / steps[0])
            for j in range(m):
                ex[j] = ow[j] > _line(line, max(f64(s00[j] * inv0), 0.0)) * excess_limit
        blur[:, :, :m] = 0.0
        for k in range(n_sets):
            ax = set_axis[k]
            _set_block(sums, row0[k], nrows[k], steps[k], periods[k], amps[k], line, params,
                       j0, m,
                       ow, ex, wrapped[k], sig[k], use[k], blur[:, ax], snr_a[:, ax],
                       k == first[ax], lg, lg_e, lg_m, wt)
        _contrast(bright, dark, flats, line, mode, j0, m, ow, snr)
        for ax in range(2):
            _blur_fit(blur[:, ax], m)
        unwrap_block(m, wrapped, sig, use, blur, snr_a, snr, d, first, set_axis, periods,
                     chi2_limit, extents, params, pos_out, sig_out, mod_out, blur_out,
                     o0 + b0, reason[b0:b0 + m], state)
        for j in range(m):  # every step clipped in every set: no fit (phase.fit_set)
            if dd[j]:
                q = 0.0 if mode == MODE_OWN else snr[j]  # (no residual dof: no noise level)
                reason[b0 + j] = 1 if not q >= params[P_MIN_CONTRAST] else 2
                for ax in range(2):
                    if first[ax] >= 0:
                        mod_out[ax, o0 + b0 + j] = 0.0
        clipped_block(m, d, dd, sums, bits, squares, bright, dark, j0, row0, nrows, steps,
                      tables, mode, line, noise[N_FLOOR], tail, leak, flats, set_axis,
                      periods, amps, chi2_limit, extents, params, pos_out, sig_out, mod_out,
                      blur_out, o0 + b0, reason[b0:b0 + m])


@njit(cache=True, error_model="numpy", nogil=True)
def residual_stats(sums, bits, squares, c0, row0, nrows, steps, level_out, rss_out, dof_out,
                   dirty_out, power_out, low_out, bright, dark, clip, leak, tables) -> None:
    """Residual-mode first pass (decoder `_residuals`) for the pixels of columns c0..:
    dof-weighted level, residual sum of squares, residual dof, each set's Nyquist power;
    `dirty_out` marks the pixels with clipped steps. With `tables` (non-empty index) those
    are fitted here too (kernel_clipped.py; `clip`: floor, bright and dark flat counts,
    min_contrast_snr) and `low_out` marks a step clipped at the dark end; without, they
    are left to the array path (`low_out` untouched)."""
    n = level_out.shape[0]
    expl, own, lev = np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK)
    dof = 0.0
    for k in range(row0.shape[0]):
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
        for j in range(m):
            own[j] = float(squares[j0 + j])
            lev[j] = 0.0
        for k in range(row0.shape[0]):
            _explained(sums, row0[k], nrows[k], steps[k], j0, m, expl)
            dof_k = np.float32(steps[k] - nrows[k])
            s0 = sums[row0[k], j0:j0 + m]
            inv_n = np.float32(1.0 / steps[k])
            for j in range(m):
                own[j] -= expl[j]
                lev[j] += dof_k * (s0[j] * inv_n)
            _nyquist(sums, row0[k], steps[k], j0, m, expl)
            power_out[k, b0:b0 + m] = expl[:m]
        for j in range(m):
            rss_out[b0 + j] = max(own[j], 0.0)
            level_out[b0 + j] = lev[j] / max(dof, 1.0)
            dof_out[b0 + j] = dof
            low_out[b0 + j] = False
        if tables[0].shape[0] == 0:
            continue
        fit, p = np.empty((row0.shape[0], 12)), np.empty((row0.shape[0], tables[2].shape[2]))
        for j in range(m):
            if d[j]:
                level_out[b0 + j], rss_out[b0 + j], dof_out[b0 + j], _, kept = clipped_residuals(
                    sums, bits, squares, bright, dark, j0 + j, row0, nrows, steps, tables[0],
                    tables[1], tables[2], clip[0], clip[1:3], clip[3], leak, fit, p, power_out,
                    b0 + j)
                low_out[b0 + j] = not kept  # (kept: no step clipped at the dark end)


@njit(cache=True, error_model="numpy", inline="always")
def _nyquist(sums, r0, steps, j0, m, out) -> None:
    """out[:m] = noise.nyquist_power_of one set (float32 arithmetic as there; unclipped)."""
    f32 = np.float32
    scale = f32(2.0 / steps)
    sa, sb = sums[r0 + 1, j0:j0 + m], sums[r0 + 2, j0:j0 + m]
    for j in range(m):
        if steps % 2:
            out[j] = 0.0
            continue
        a, b = sa[j] * scale, sb[j] * scale
        b2 = a * a + b * b
        u = b / math.sqrt(b2 if b2 > 0 else f32(1.0))
        prev, cheb = f32(1.0), u
        for _ in range(steps // 2 - 1):
            prev, cheb = cheb, f32(2.0) * u * cheb - prev
        out[j] = f32(steps) * b2 * cheb * cheb


@njit(cache=True, error_model="numpy", inline="always")
def _explained(sums, r0, nrow, steps, j0, m, expl) -> None:
    """expl[:m] = the part of sum v^2 one set's fit explains, as fit_set computes it (the
    same additions in the same order: the photon-transfer line sees the same residuals)."""
    s0 = sums[r0, j0:j0 + m]
    two = 2.0 / steps
    if nrow == 7:  # one pass over the rows (residual mode, >= 8 steps: harmonics 2 and 3)
        r1, r2, r3 = sums[r0 + 1, j0:j0 + m], sums[r0 + 2, j0:j0 + m], sums[r0 + 3, j0:j0 + m]
        r4, r5, r6 = sums[r0 + 4, j0:j0 + m], sums[r0 + 5, j0:j0 + m], sums[r0 + 6, j0:j0 + m]
        for j in range(m):
            e = float(s0[j]) ** 2 / steps
            e += float(r1[j]) ** 2 * two
            e += float(r2[j]) ** 2 * two
            e += float(r3[j]) ** 2 * two
            e += float(r4[j]) ** 2 * two
            e += float(r5[j]) ** 2 * two
            expl[j] = e + float(r6[j]) ** 2 * two
        return
    for j in range(m):
        expl[j] = float(s0[j]) ** 2 / steps
    for r in range(1, nrow):
        row = sums[r0 + r, j0:j0 + m]
        for j in range(m):
            expl[j] += float(row[j]) ** 2 * (2.0 / steps)


@njit(cache=True, error_model="numpy", inline="always")
def _set_block(sums, r0, nrow, steps, period, amp, line, params, j0, m, own, excess, wrapped,
               sig, use, blur, anchor, is_first, lg, lg_e, lg_m, wt) -> None:
    """One set over a block: variance, modulation, sigmas, wrapped position, blur terms.
    Branch-free loops (error_model numpy: no division-by-zero checks) LLVM vectorizes.
    All steps kept: the (alpha, beta) covariance is c I (phase.SetFit `_isotropic`), so
    the modulation variance is c and the phase variance c / B^2."""
    f32 = np.float32
    inv_n, scale = f32(1.0 / steps), f32(2.0 / steps)
    c = float(f32(2.0 / steps))  # covariance factor of alpha and beta, all steps kept
    psnr = params[P_PERIOD_SNR]
    to_px = f32(period / (2.0 * math.pi))
    s0, sa, sb = sums[r0, j0:j0 + m], sums[r0 + 1, j0:j0 + m], sums[r0 + 2, j0:j0 + m]
    var = lg_e  # scratch: the sample variance of this set (float32 values)
    if nrow > 3:  # harmonic 2 modelled: noise.phase_level, the level at the crossings
        s2r, c2r = sums[r0 + 3, j0:j0 + m], sums[r0 + 4, j0:j0 + m]
        for j in range(m):
            a, b = sa[j] * scale, sb[j] * scale
            s2, c2 = s2r[j] * scale, c2r[j] * scale
            b2 = a * a + b * b
            h2c = (c2 * (b * b - a * a) + s2 * f32(2.0) * a * b) / (b2 if b2 > 0 else f32(1.0))
            level = max(s0[j] * inv_n - f32(0.5) * h2c, f32(0.0))
            var[j] = float(f32(own[j] if excess[j] else _line(line, float(level))))
    else:
        for j in range(m):
            level = max(s0[j] * inv_n, f32(0.0))
            var[j] = float(f32(own[j] if excess[j] else _line(line, float(level))))
    snr_row, mod_row = anchor[0], anchor[1]
    inv_amp2 = 1.0 / (amp * amp)
    for j in range(m):  # what kernel.decode_pixel computes per set, vectorized
        a, b = float(sa[j] * scale), float(sb[j] * scale)
        b2 = a * a + b * b
        mod = math.sqrt(b2)
        vc = var[j] * c  # s_b^2
        s_b = math.sqrt(vc)
        # sigma of the wrapped position: period / 2 pi * sqrt(var c / B^2) (no phase at B 0)
        sig_c = (period / _TWO_PI) * (s_b / (mod if b2 != 0.0 else 1e-15))
        strong = mod >= psnr * s_b
        ok = strong and sig_c < np.inf
        sig[j] = sig_c if ok else period
        use[j] = ok
        fit = strong and s_b > 0.0 and mod > 0.0
        corr2 = max(b2 - 2.0 * vc, 0.25 * b2)  # the bias-corrected modulation, squared
        wt[j] = corr2 / vc if fit else 0.0
        lg[j] = corr2 * inv_amp2 if fit else 1.0  # (corr / amp)^2: its log halved below
        if is_first:
            snr_row[j] = mod / s_b if s_b > 0 else 0.0
        mod_row[j] = mod
    for j in range(m):
        w = atan2_f32(-(sa[j] * scale), sb[j] * scale) * to_px  # (float32 lanes, as NumPy's)
        wrapped[j] = w + f32(period) if w < 0 else w
    log_inplace(lg[:m], lg_e[:m], lg_m[:m])
    x = 1.0 / (period * period)
    for j in range(m):
        w = wt[j]
        y = 0.5 * lg[j]
        blur[0, j] += w
        blur[1, j] += w * x
        blur[2, j] += w * y
        blur[3, j] += w * x * x
        blur[4, j] += w * x * y
        blur[5, j] += 1.0 if w > 0.0 else 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _contrast(bright, dark, flats, line, mode, j0, m, own, snr) -> None:
    """snr[:m] = bright-minus-dark flat contrast over its noise (0 where not finite)."""
    for j in range(m):
        lit = bright[j0 + j] / flats[0]
        unlit = dark[j0 + j] / flats[1]
        if mode == MODE_OWN:
            var_b = var_d = own[j]
        else:
            var_b, var_d = _line(line, lit), _line(line, max(unlit, 0.0))
        q = (lit - unlit) / math.sqrt(var_b / flats[0] + var_d / flats[1])
        snr[j] = q if abs(q) < np.inf else 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _blur_fit(blur, m) -> None:
    """Replace the blur line sums by the fitted blur width (row 0; NaN where not fitted)."""
    for j in range(m):
        sw, sx, sy, sxx, sxy = blur[0, j], blur[1, j], blur[2, j], blur[3, j], blur[4, j]
        det = sw * sxx - sx * sx
        fitted = blur[5, j] >= 2 and det > 0
        slope = -((sw * sxy - sx * sy) / (det if fitted else 1.0)) / (2.0 * math.pi**2)
        blur[0, j] = math.sqrt(max(slope, 0.0)) if fitted else np.nan


drop_stale_kernels(globals())  # before any kernel runs: no machine code from older sources
