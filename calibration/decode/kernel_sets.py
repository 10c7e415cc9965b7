"""One period set over a block of pixels (numba), for kernel_sums.py: noise variance,
modulation, sigmas, wrapped position and blur terms as loops LLVM vectorizes.

Two forms of the same arithmetic as kernel.py's `decode_pixel`: `set_block` reads an
unclipped block's fits straight from the sums (covariance c I: phase.SetFit `_isotropic`);
`general_set_block` reads per-pixel fits and a general (c_aa, c_bb, c_ab) covariance
(pixels with clipped steps, kernel_clipped.py), isotropic pixels keeping the first form's
rounding.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.decode.kernel import P_PERIOD_SNR
from calibration.decode.kernel_cache import drop_stale_kernels
from calibration.decode.vecmath import atan2_f32, log_inplace

_TWO_PI = 2.0 * math.pi

# Indices of `noise`: the noise mode and the linear variance model's coefficients.
N_MODE, N_OFFSET, N_SLOPE, N_BLACK, N_CLAMP, N_FLOOR, N_LINE_FLOOR = range(7)
MODE_GIVEN, MODE_LINE, MODE_OWN = 0, 1, 2  # given model / photon-transfer line / own residual


@njit(cache=True, error_model="numpy", inline="always")
def line_var(line, level: float) -> float:
    """Variance of the linear noise model `line` (`line_of`) at `level`: offset + slope *
    (level - black)+, at least the line's floor (a photon-transfer line: quantization)."""
    offset, slope, black, clamp, floor = line
    x = level - black
    x = 0.0 if clamp and not x > 0.0 else x
    return max(offset + slope * x, floor)


@njit(cache=True, error_model="numpy", inline="always")
def line_of(noise):
    """The linear model of `noise` as scalars (offset, slope, black, clamp, floor): loops
    that read them from the array reload them per pixel (possible aliasing) and stay scalar."""
    return (noise[N_OFFSET], noise[N_SLOPE], noise[N_BLACK], noise[N_CLAMP] != 0.0,
            noise[N_LINE_FLOOR])


@njit(cache=True, error_model="numpy", inline="always")
def nyquist(sums, r0, steps, j0, m, out) -> None:
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
def explained(sums, r0, nrow, steps, j0, m, expl) -> None:
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
def set_variance(sums, r0, nrow, steps, line, j0, m, mean, alpha, beta, own, excess, var):
    """var[:m] = the set's sample variance (float32 values): `own` where `excess`, else the
    line at the phase's level (noise.phase_level: the mean less half the second harmonic
    in phase with the fundamental, from the raw harmonic-2 sums and the fitted alpha, beta)."""
    f32 = np.float32
    scale = f32(2.0 / steps)
    if nrow > 3:
        s2r, c2r = sums[r0 + 3, j0:j0 + m], sums[r0 + 4, j0:j0 + m]
        for j in range(m):
            a, b = alpha[j], beta[j]
            s2, c2 = s2r[j] * scale, c2r[j] * scale
            b2 = a * a + b * b
            h2c = (c2 * (b * b - a * a) + s2 * f32(2.0) * a * b) / (b2 if b2 > 0 else f32(1.0))
            level = max(mean[j] - f32(0.5) * h2c, f32(0.0))
            var[j] = float(f32(own[j] if excess[j] else line_var(line, float(level))))
    else:
        for j in range(m):
            level = max(mean[j], f32(0.0))
            var[j] = float(f32(own[j] if excess[j] else line_var(line, float(level))))


@njit(cache=True, error_model="numpy", inline="always")
def set_block(sums, r0, nrow, steps, period, amp, line, params, j0, m, own, excess, wrapped,
              sig, use, blur, anchor, is_first, lg, lg_e, lg_m, wt) -> None:
    """One unclipped set over a block: variance, modulation, sigmas, wrapped position,
    blur terms. All steps kept: the (alpha, beta) covariance is c I, so the modulation
    variance is c and the phase variance c / B^2."""
    f32 = np.float32
    inv_n, scale = f32(1.0 / steps), f32(2.0 / steps)
    c = float(f32(2.0 / steps))  # covariance factor of alpha and beta, all steps kept
    psnr = params[P_PERIOD_SNR]
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
            var[j] = float(f32(own[j] if excess[j] else line_var(line, float(level))))
    else:
        for j in range(m):
            level = max(s0[j] * inv_n, f32(0.0))
            var[j] = float(f32(own[j] if excess[j] else line_var(line, float(level))))
    snr_row, mod_row, ok_row = anchor[0], anchor[1], anchor[2]
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
            ok_row[j] = 1.0
        mod_row[j] = mod
    _phase_blur(sa, sb, scale, period, m, wrapped, blur, lg, lg_e, lg_m, wt)


@njit(cache=True, error_model="numpy", inline="always")
def general_set_block(alpha, beta, mean, fitted, cov, partial, sums, r0, nrow, steps, period,
                      amp, line, params, j0, m, own, excess, wrapped, sig, use, blur, anchor,
                      is_first, lg, lg_e, lg_m, wt) -> None:
    """One set over a block from per-pixel fits (kernel_clipped.fit_block: `alpha`, `beta`,
    `mean` float32, `fitted`; `cov` rows c_aa, c_bb, c_ab per unit variance, then the
    use_step_levels numerators, taken where `partial` and the line holds): the arithmetic
    of kernel.decode_pixel per set, vectorized. Isotropic pixels (c_ab 0, c_aa = c_bb)
    are computed as in `set_block`."""
    f32 = np.float32
    psnr = params[P_PERIOD_SNR]
    var = lg_e  # scratch: the sample variance of this set (float32 values)
    set_variance(sums, r0, nrow, steps, line, j0, m, mean, alpha, beta, own, excess, var)
    c_aa, c_bb, c_ab = cov[0], cov[1], cov[2]
    for j in range(m):  # SetFit.use_step_levels: each kept step's own noise variance
        if partial[j] and not excess[j] and var[j] > 0:
            c_aa[j] = float(f32(cov[3, j] / var[j]))
            c_bb[j] = float(f32(cov[4, j] / var[j]))
            c_ab[j] = float(f32(cov[5, j] / var[j]))
    snr_row, mod_row, ok_row = anchor[0], anchor[1], anchor[2]
    inv_amp2 = 1.0 / (amp * amp)
    for j in range(m):
        a, b = float(alpha[j]), float(beta[j])
        b2 = a * a + b * b
        mod = math.sqrt(b2)
        v = var[j]
        caa, cbb, cab = c_aa[j], c_bb[j], c_ab[j]
        iso = cab == 0.0 and caa == cbb
        some = b2 != 0.0
        inv = 1.0 / (b2 if some else 1.0)
        mod_var = (a * a * caa + 2.0 * a * b * cab + b * b * cbb) * inv
        mod_var = caa if iso else (mod_var if some else 0.5 * (caa + cbb))
        ph_var = (b * b * caa - 2.0 * a * b * cab + a * a * cbb) * (inv * inv)
        vc = v * mod_var  # s_b^2
        s_b = math.sqrt(vc)
        iso_sig = s_b / (mod if some else 1e-15)
        gen_sig = math.sqrt(v * (ph_var if some else 1e30))
        sig_c = (period / _TWO_PI) * (iso_sig if iso else gen_sig)
        strong = mod >= psnr * s_b
        ok = fitted[j] and strong and sig_c < np.inf
        sig[j] = sig_c if ok else period
        use[j] = ok
        fit = strong and s_b > 0.0 and mod > 0.0
        corr2 = max(b2 - 2.0 * vc, 0.25 * b2)
        wt[j] = corr2 / vc if fit else 0.0
        lg[j] = corr2 * inv_amp2 if fit else 1.0
        if is_first:
            snr_row[j] = mod / s_b if s_b > 0 else 0.0
            ok_row[j] = 1.0 if fitted[j] else 0.0
        mod_row[j] = mod
    _phase_blur(alpha, beta, f32(1.0), period, m, wrapped, blur, lg, lg_e, lg_m, wt)


@njit(cache=True, error_model="numpy", inline="always")
def _phase_blur(sa, sb, scale, period, m, wrapped, blur, lg, lg_e, lg_m, wt) -> None:
    """Wrapped positions from alpha = sa * scale, beta = sb * scale (float32 lanes, as
    NumPy's float32 arctan2), then the blur line sums of weights `wt` and values log(lg)/2."""
    f32 = np.float32
    to_px = f32(period / (2.0 * math.pi))
    for j in range(m):
        w = atan2_f32(-(sa[j] * scale), sb[j] * scale) * to_px
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
def contrast(bright, dark, flats, line, own_mode, j0, m, own, snr) -> None:
    """snr[:m] = bright-minus-dark flat contrast over its noise (0 where not finite)."""
    lit_row, unlit_row = bright[j0:j0 + m], dark[j0:j0 + m]  # (views: the loop vectorizes)
    for j in range(m):
        lit = lit_row[j] / flats[0]
        unlit = unlit_row[j] / flats[1]
        if own_mode:
            var_b = var_d = own[j]
        else:
            var_b, var_d = line_var(line, lit), line_var(line, max(unlit, 0.0))
        q = (lit - unlit) / math.sqrt(var_b / flats[0] + var_d / flats[1])
        snr[j] = q if abs(q) < np.inf else 0.0


@njit(cache=True, error_model="numpy", inline="always")
def blur_fit(blur, m) -> None:
    """Replace the blur line sums by the fitted blur width (row 0; NaN where not fitted)."""
    for j in range(m):
        sw, sx, sy, sxx, sxy = blur[0, j], blur[1, j], blur[2, j], blur[3, j], blur[4, j]
        det = sw * sxx - sx * sx
        fitted = blur[5, j] >= 2 and det > 0
        slope = -((sw * sxy - sx * sy) / (det if fitted else 1.0)) / (2.0 * math.pi**2)
        blur[0, j] = math.sqrt(max(slope, 0.0)) if fitted else np.nan


drop_stale_kernels(globals())  # before any kernel runs: no machine code from older sources
