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

from calibration.decode.kernel import decode_pixel

DIRTY = 255  # reason code of pixels this kernel leaves to the array path

# Indices of `noise`: the noise mode and the linear variance model's coefficients.
N_MODE, N_OFFSET, N_SLOPE, N_BLACK, N_CLAMP, N_FLOOR = range(6)
MODE_GIVEN, MODE_LINE, MODE_OWN = 0, 1, 2  # given model / photon-transfer line / own residual


@njit(cache=True, inline="always")
def _line(noise, level: float) -> float:
    """Variance of the linear noise model at `level`: offset + slope * (level - black)+."""
    x = level - noise[N_BLACK]
    if noise[N_CLAMP] != 0.0 and not x > 0.0:
        x = 0.0
    return noise[N_OFFSET] + noise[N_SLOPE] * x


@njit(cache=True, inline="always")
def _set_fit(sums, r0, nrow, steps, i, residual):
    """Closed-form fit of one set at pixel i: (mean, alpha, beta) float32 and the part of
    sum v^2 it explains (float64; 0 unless `residual`)."""
    s0 = sums[r0, i]
    mean = s0 * np.float32(1.0 / steps)
    scale = np.float32(2.0 / steps)
    alpha = sums[r0 + 1, i] * scale
    beta = sums[r0 + 2, i] * scale
    explained = 0.0
    if residual:
        explained = float(s0) ** 2 / steps
        for r in range(1, nrow):
            explained += float(sums[r0 + r, i]) ** 2 * (2.0 / steps)
    return mean, alpha, beta, explained


@njit(cache=True, inline="always")
def _dirty(bits, i) -> bool:
    """Any clipped step in any set at pixel i."""
    for k in range(bits.shape[0]):
        if bits[k, i] != 0:
            return True
    return False


@njit(cache=True, nogil=True)
def residual_stats(sums, bits, squares, row0, nrows, steps, level_out, rss_out, dof_out,
                   dirty_out) -> None:
    """Residual-mode first pass (decoder `_residuals`) for unclipped pixels: dof-weighted
    level, residual sum of squares, residual dof; `dirty_out` marks the others."""
    for i in range(squares.shape[0]):
        if _dirty(bits, i):
            dirty_out[i] = True
            continue
        dirty_out[i] = False
        rss = float(squares[i])
        dof = level = 0.0
        for k in range(row0.shape[0]):
            mean, _, _, explained = _set_fit(sums, row0[k], nrows[k], steps[k], i, True)
            dof_k = np.float32(steps[k] - nrows[k])
            rss -= explained
            dof += dof_k
            level += dof_k * mean
        level_out[i] = level / max(dof, 1.0)
        rss_out[i] = max(rss, 0.0)
        dof_out[i] = dof


@njit(cache=True, nogil=True)  # no fastmath: NaN and infinity tests matter here
def finish_sums(
    sums, bits, squares, bright, dark,  # (M, n), (S, n), (n,) or (0,), (n,), (n,)
    row0, nrows, steps,  # (S,) int64 set layout in `sums`
    noise,  # (6,) see N_* indices
    flats,  # (2,) number of bright and dark flats
    tail,  # (D + 1,) chi2.isf(1e-6, d) / d by residual dof d (residual mode)
    set_axis, periods, amps, chi2_limit, extents, params,  # as kernel.finish_pixels
    pos_out, sig_out, mod_out, blur_out, reason,
) -> None:
    """Decode the unclipped pixels of a chunk from its sums; others get reason DIRTY."""
    n_sets = row0.shape[0]
    mode = int(noise[N_MODE])
    residual = mode != MODE_GIVEN
    f32 = np.float32
    mean = np.empty(n_sets, dtype=f32)
    alpha = np.empty(n_sets, dtype=f32)
    beta = np.empty(n_sets, dtype=f32)
    wrapped = np.empty(n_sets, dtype=f32)
    var = np.empty(n_sets, dtype=f32)
    c_diag = np.empty(n_sets, dtype=f32)
    c_off = np.zeros(n_sets, dtype=f32)
    ok = np.ones(n_sets, dtype=np.bool_)
    for k in range(n_sets):
        c_diag[k] = f32(2.0 / steps[k])
    for i in range(bright.shape[0]):
        if _dirty(bits, i):
            reason[i] = DIRTY
            continue
        rss = float(squares[i]) if residual else 0.0
        dof = 0.0
        for k in range(n_sets):
            m, a, b, explained = _set_fit(sums, row0[k], nrows[k], steps[k], i, residual)
            mean[k], alpha[k], beta[k] = m, a, b
            rss -= explained
            dof += steps[k] - nrows[k]
        own = math.nan
        if dof > 0:
            own = max(max(rss, 0.0) / max(dof, 1.0), noise[N_FLOOR])
        excess = False
        if mode == MODE_LINE:
            excess = own > _line(noise, max(float(mean[0]), 0.0)) * tail[int(dof)]
        for k in range(n_sets):
            if mode == MODE_OWN or excess:
                var[k] = own
            else:
                var[k] = _line(noise, max(float(mean[k]), 0.0))
            phi = math.atan2(-alpha[k], beta[k])
            w = f32(phi) * f32(periods[k] / (2.0 * math.pi))
            wrapped[k] = w + f32(periods[k]) if w < 0 else w
        lit = bright[i] / flats[0]
        unlit = dark[i] / flats[1]
        if mode == MODE_OWN:
            var_b = var_d = own
        else:
            var_b, var_d = _line(noise, lit), _line(noise, max(unlit, 0.0))
        snr = (lit - unlit) / math.sqrt(var_b / flats[0] + var_d / flats[1])
        if not math.isfinite(snr):
            snr = 0.0
        reason[i] = decode_pixel(alpha, beta, wrapped, var, c_diag, c_diag, c_off, ok, snr,
                                 set_axis, periods, amps, chi2_limit, extents, params,
                                 pos_out, sig_out, mod_out, blur_out, i)
