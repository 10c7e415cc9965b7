"""Compiled per-pixel finish (numba): phase, sigma, unwrapping, blur and validity in one pass.

The same arithmetic as phase.py (position, variances), unwrap.py (`fuse_axis`), blur.py
(`fit_blur`) and validity.py (`classify`), written per pixel so that a pixel's dozens of
intermediate values stay in registers instead of in full-chunk temporary arrays (the
NumPy path makes ~200 passes over each chunk). The decoder uses it for NumPy arrays; CuPy
arrays take the array-namespace path. Compiled once per machine (cached next to the code).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.decode.kernel_cache import drop_stale_kernels

# Gaussian-mass cut-off and merge distance of unwrap.py, duplicated as compile-time constants
# (FAR_SIGMA, TOOTH_CUTOFF, `coarsest_order` and `fuse_period` are public: kernel_unwrap.py's
# block loops use the same ones, so both kernels give the same result for a pixel).
FAR_SIGMA = 8.5
_MERGE_SIGMA = 2.0
_TWO_PI = 2.0 * math.pi
# A finer period's neighbouring teeth weigh exp(-x) relative to the nearest one; below
# exp(-69) < 1e-30 they move no position, sigma or ambiguity by anything a map can hold
# (a shift of < 1e-30 period): taken as 0, without calling exp. (The float64 underflow
# limit, 740, sent every pixel of a realistically noisy pose on a period ratio of 8 to
# the scalar fusion: the finish took twice as long.)
TOOTH_CUTOFF = 69.0
_SQRT1_2 = 1.0 / math.sqrt(2.0)

# Indices of `params` (DecodeOptions values and the per-period SNR floor).
P_MIN_CONTRAST, P_MIN_MOD, P_MAX_AMB, P_MARGIN_SIGMA, P_EDGE_BLUR, P_MAX_SIGMA, P_PERIOD_SNR = (
    range(7)
)


@njit(cache=True, error_model="numpy", inline="always")
def _ndtr(x: float) -> float:
    """Standard normal CDF."""
    return 0.5 * math.erfc(-x * _SQRT1_2)


@njit(cache=True, error_model="numpy")
def coarsest_order(c: float, sigma: float, period: float, lo: float, hi: float
                   ) -> tuple[float, float]:
    """Order of the coarsest period under a uniform prior on [lo, hi]: (mu, ambiguity)."""
    in_lo = min(hi - c + period, c - period - lo)
    in_0 = min(hi - c, c - lo)
    in_hi = min(hi - c - period, c + period - lo)
    mu = c if in_0 >= in_lo else c - period
    if in_hi > max(in_0, in_lo):
        mu = c + period
    reach = FAR_SIGMA * sigma
    if not (abs(in_lo) < reach or abs(in_0) < reach or abs(in_hi) < reach):
        return mu, 0.0
    top = -1.0
    total = 0.0
    for k in range(3):
        sub = c + period * (k - 1.0)
        mass = _ndtr((hi - sub) / sigma) - _ndtr((lo - sub) / sigma)
        total += mass
        if mass > top:
            top = mass
            mu = sub
    return mu, (1.0 - top / total) if total > 0 else 1.0


@njit(cache=True, error_model="numpy", nogil=True, fastmath=True)
def finish_pixels(
    alpha, beta, wrapped, var, c_aa, c_bb, c_ab, ok,  # (S, n) per period set
    set_axis, periods, amps,  # (S,) axis 0/1, period px, pattern amplitude
    contrast_snr,  # (n,)
    chi2_limit,  # (S + 1,) chi-square limit by number of fused finer periods
    extents,  # (2,) screen extent px per axis
    params,  # (7,) see P_* indices
    pos_out, sig_out, mod_out, blur_out,  # (2, n) outputs, rows of absent axes untouched
    reason,  # (n,) uint8 out
) -> None:
    """Decode a chunk of pixels from their per-set fits (float32 inputs, float64 arithmetic)."""
    for i in range(contrast_snr.shape[0]):
        reason[i] = decode_pixel(
            alpha[:, i], beta[:, i], wrapped[:, i], var[:, i], c_aa[:, i], c_bb[:, i],
            c_ab[:, i], ok[:, i], contrast_snr[i], set_axis, periods, amps, chi2_limit,
            extents, params, pos_out, sig_out, mod_out, blur_out, i)


@njit(cache=True, error_model="numpy", nogil=True, fastmath=True)
def decode_pixel(
    alpha, beta, wrapped, var, c_aa, c_bb, c_ab, ok,  # (S,) one pixel's per-set fits
    contrast_snr, set_axis, periods, amps, chi2_limit, extents, params,
    pos_out, sig_out, mod_out, blur_out, i,
) -> int:
    """Unwrap, sigma, blur and validity of pixel `i` (outputs at column i); its reason code."""
    n_sets = periods.shape[0]
    period_snr = params[P_PERIOD_SNR]
    code = 99 if contrast_snr >= params[P_MIN_CONTRAST] else 1  # 99: no rule failed
    for ax in range(2):
        first = -1
        mu = var_mu = chi2 = amb = 0.0
        dof = 0
        sw = sx = sy = sxx = sxy = 0.0
        count = 0
        mod = anchor_snr = 0.0
        anchor_ok = True
        for k in range(n_sets):
            if set_axis[k] != ax:
                continue
            period = periods[k]
            a = float(alpha[k])
            b = float(beta[k])
            v = float(var[k])
            caa, cbb, cab = float(c_aa[k]), float(c_bb[k]), float(c_ab[k])
            b2 = a * a + b * b
            mod = math.sqrt(b2)
            if b2 == 0.0:
                mod_var = 0.5 * (caa + cbb)
                ph_var = 1e30
            else:
                inv = 1.0 / b2
                mod_var = (a * a * caa + 2.0 * a * b * cab + b * b * cbb) * inv
                ph_var = (b * b * caa - 2.0 * a * b * cab + a * a * cbb) * (inv * inv)
            s_b = math.sqrt(v * mod_var)
            sig_c = (period / _TWO_PI) * math.sqrt(v * ph_var)
            use = ok[k] and mod >= period_snr * s_b and math.isfinite(sig_c)
            c = float(wrapped[k])
            sig = sig_c if use else period
            # blur line fit (blur.py)
            if mod >= period_snr * s_b and s_b > 0 and mod > 0:
                corr = math.sqrt(max(mod * mod - 2.0 * s_b * s_b, 0.25 * mod * mod))
                w = corr * corr / (s_b * s_b)
                y = math.log(corr / amps[k])
                x = 1.0 / (period * period)
                sw += w
                sx += w * x
                sy += w * y
                sxx += w * x * x
                sxy += w * x * y
                count += 1
            if first < 0:  # coarsest period: the anchor
                first = k
                anchor_ok = ok[k]
                anchor_snr = mod / s_b if s_b > 0 else 0.0
                mu, amb = coarsest_order(c, sig, period, -0.5, extents[ax] - 0.5)
                var_mu = sig * sig
                continue
            if not use:
                continue
            mu, var_mu, innovation, amb_k = fuse_period(mu, var_mu, c, sig, period)
            chi2 += innovation
            dof += 1
            amb += amb_k * (1.0 - amb)
        if first < 0:
            continue  # the plan has no frames on this axis
        sigma = math.sqrt(var_mu)
        det = sw * sxx - sx * sx
        blur = np.nan
        if count >= 2 and det > 0:
            blur = math.sqrt(max(-((sw * sxy - sx * sy) / det) / (2.0 * math.pi**2), 0.0))
        pos_out[ax, i] = mu
        sig_out[ax, i] = sigma
        mod_out[ax, i] = mod
        blur_out[ax, i] = blur
        rule = _axis_rule(anchor_ok, anchor_snr, amb, chi2, chi2_limit[dof], mu, sigma,
                          blur, extents[ax], params)
        code = min(code, rule)  # the first rule that fails on any axis names the reason
    return 0 if code == 99 else code


@njit(cache=True, error_model="numpy", inline="always")
def fuse_period(mu: float, var_mu: float, c: float, sig: float, period: float):
    """One finer period into the Gaussian posterior N(mu, var_mu) (unwrap.py `fuse_axis`):
    (new mu, new variance, innovation chi-square, ambiguity of this step)."""
    var_k = sig * sig
    inv_total = 1.0 / (var_mu + var_k)
    d0 = mu - c
    d0 -= np.rint(d0 * (1.0 / period)) * period
    gain = var_mu * inv_total
    post_var = gain * var_k
    half = 0.5 * period * period * inv_total
    tilt = d0 * period * inv_total
    # negligible teeth (`TOOTH_CUTOFF`): no exp (nor libm's slow underflow path)
    w_lo = math.exp(-(half + tilt)) if half + tilt < TOOTH_CUTOFF else 0.0
    w_hi = math.exp(tilt - half) if half - tilt < TOOTH_CUTOFF else 0.0
    step = period * gain
    new_mu = mu - d0 * gain
    if step * step > _MERGE_SIGMA * _MERGE_SIGMA * post_var:
        amb_k = (w_lo + w_hi) / (1.0 + w_lo + w_hi)
    else:
        amb_k = 0.0
        norm = 1.0 + w_lo + w_hi
        shift = (w_hi - w_lo) * step / norm
        spread = (w_lo * (step + shift) ** 2 + w_hi * (step - shift) ** 2
                  + shift * shift) / norm
        new_mu += shift
        post_var += spread
    return new_mu, post_var, d0 * d0 * inv_total, amb_k


@njit(cache=True, error_model="numpy", inline="always")
def _axis_rule(anchor_ok, anchor_snr, amb, chi2, limit, mu, sigma, blur, extent, params) -> int:
    """First failed validity rule of one axis (validity.REASONS code), 99 when all pass."""
    if not anchor_ok:
        return 2
    if not anchor_snr >= params[P_MIN_MOD]:
        return 3
    if not amb <= params[P_MAX_AMB]:
        return 4
    if not chi2 <= limit:
        return 5
    margin = params[P_MARGIN_SIGMA] * sigma
    if not (mu >= -0.5 - margin and mu <= extent - 0.5 + margin):
        return 6
    reach = params[P_EDGE_BLUR] * (blur if math.isfinite(blur) else 0.0)
    if not (mu + 0.5 >= reach and extent - 0.5 - mu >= reach):
        return 7
    if not sigma <= params[P_MAX_SIGMA]:
        return 8
    return 99


def warm_up() -> None:
    """Load (or compile) the kernel for the argument types the decoder passes, on one pixel:
    a live capture does this while frames arrive, not after the last one."""
    f32 = np.ones((1, 1), dtype=np.float32)
    planes = [np.zeros((2, 2), dtype=dt)[:, :1] for dt in (np.float64, np.float32, np.float32,
                                                            np.float32)]
    finish_pixels(f32, f32, f32, f32, f32, f32, f32, np.ones((1, 1), dtype=np.bool_),
                  np.zeros(1, dtype=np.int64), np.ones(1), np.ones(1), np.ones(1),
                  np.full(2, np.inf), np.ones(2), np.ones(7), *planes,
                  np.zeros(1, dtype=np.uint8))


drop_stale_kernels(globals())  # before any kernel runs: no machine code from older sources
