"""Vectorized unwrapping and validity rules over a block of pixels (numba): the same
arithmetic as kernel.py's per-pixel `coarsest_order`, `fuse_period` and `_axis_rule`, written as
loops over the block's pixels that LLVM vectorizes. The rare pixels that need the
Gaussian masses at a screen end or the exponential weights of neighbouring teeth are
redone by the scalar functions (exactly the same results)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.decode.kernel import (
    FAR_SIGMA,
    P_EDGE_BLUR,
    P_MARGIN_SIGMA,
    P_MAX_AMB,
    P_MAX_SIGMA,
    P_MIN_CONTRAST,
    P_MIN_MOD,
    TOOTH_CUTOFF,
    coarsest_order,
    fuse_period,
)
from calibration.decode.kernel_cache import drop_stale_kernels

# rows of the `state` scratch: posterior mean and variance, chi-square, fused periods,
# ambiguity, the next mean and variance, and a per-pixel flag
S_MU, S_VAR, S_CHI2, S_DOF, S_AMB, S_MU2, S_VAR2, S_FLAG, S_CODE = range(9)
STATE_ROWS = 9


@njit(cache=True, error_model="numpy", nogil=True)
def unwrap_block(m, wrapped, sig, use, blur, anchor, snr, dirty, first, set_axis, periods,
                 chi2_limit, extents, params, pos_out, sig_out, mod_out, blur_out, o0,
                 reason, state) -> None:
    """Fuse each axis's periods for block pixels 0..m (outputs at columns o0..); reason
    codes (255 where `dirty`) into `reason[:m]`. `state`: (STATE_ROWS, >= m) scratch."""
    mu, var, chi2, dof, amb = state[S_MU], state[S_VAR], state[S_CHI2], state[S_DOF], state[S_AMB]
    flag, code = state[S_FLAG], state[S_CODE]
    for j in range(m):
        code[j] = 99.0 if snr[j] >= params[P_MIN_CONTRAST] else 1.0  # 99: no rule failed
    for ax in range(2):
        k0 = first[ax]
        if k0 < 0:
            continue  # the plan has no frames on this axis
        lo, hi, p0 = -0.5, extents[ax] - 0.5, periods[k0]
        cw, sg = wrapped[k0], sig[k0]
        for j in range(m):  # the coarsest period's order (kernel.coarsest_order's fast path)
            c = cw[j]
            in_lo = min(hi - c + p0, c - p0 - lo)
            in_0 = min(hi - c, c - lo)
            in_hi = min(hi - c - p0, c + p0 - lo)
            at = c if in_0 >= in_lo else c - p0
            mu[j] = c + p0 if in_hi > max(in_0, in_lo) else at
            reach = FAR_SIGMA * sg[j]
            near = (abs(in_lo) < reach) | (abs(in_0) < reach) | (abs(in_hi) < reach)
            flag[j] = 1.0 if near else 0.0
            var[j] = sg[j] * sg[j]
            chi2[j] = 0.0
            dof[j] = 0.0
            amb[j] = 0.0
        for j in range(m):  # (not for pixels that see no screen: see `fuse_block`)
            if flag[j] != 0.0 and code[j] != 1.0:
                mu[j], amb[j] = coarsest_order(cw[j], sg[j], p0, lo, hi)
        for k in range(k0 + 1, periods.shape[0]):
            if set_axis[k] == ax:
                fuse_block(m, wrapped[k], sig[k], use[k], periods[k], state)
        sigma_max, amb_max, margin_sigma, edge = (params[P_MAX_SIGMA], params[P_MAX_AMB],
                                                  params[P_MARGIN_SIGMA], params[P_EDGE_BLUR])
        min_mod = params[P_MIN_MOD]
        width_row, snr_row, mod_row = blur[0, ax], anchor[0, ax], anchor[1, ax]
        ok_row = anchor[2, ax]  # the anchor period fitted (1.0) or not
        # views from column o0: `row[o0 + j]` (a signed index, maybe negative to numba)
        # would keep this loop from vectorizing
        pos, sgo = pos_out[ax, o0:o0 + m], sig_out[ax, o0:o0 + m]
        mdo, blo = mod_out[ax, o0:o0 + m], blur_out[ax, o0:o0 + m]
        for j in range(m):  # outputs and the first failed rule (kernel._axis_rule)
            sigma = math.sqrt(var[j])
            width = width_row[j]
            x = mu[j]
            pos[j] = x
            sgo[j] = sigma
            mdo[j] = mod_row[j]
            blo[j] = width
            reach = edge * (width if abs(width) < np.inf else 0.0)
            margin = margin_sigma * sigma
            rule = 99.0 if sigma <= sigma_max else 8.0
            clear = (x + 0.5 >= reach) & (hi - x >= reach)
            rule = rule if clear else 7.0
            inside = (x >= -0.5 - margin) & (x <= hi + margin)
            rule = rule if inside else 6.0
            rule = rule if chi2[j] <= chi2_limit[int(dof[j])] else 5.0
            rule = rule if amb[j] <= amb_max else 4.0
            rule = rule if snr_row[j] >= min_mod else 3.0
            rule = rule if ok_row[j] != 0.0 else 2.0  # the anchor period has no fit
            code[j] = min(code[j], rule)  # the first rule that fails on any axis names it
    for j in range(m):
        reason[j] = 255 if dirty[j] else (0 if code[j] == 99.0 else int(code[j]))


@njit(cache=True, error_model="numpy", inline="always")
def fuse_block(m, cw, sg, us, period, state) -> None:
    """One finer period into the block's posteriors (kernel.fuse_period where its neighbouring
    teeth are negligible, `TOOTH_CUTOFF`; `fuse_period` itself for the other pixels, except
    those that see no screen (code 1, decided before unwrapping and final whatever the
    other rules say; their positions, sigmas and blur are NaN in the maps): ~15 % of a 5 MP
    image's pixels in the kernel, with a period-wide sigma that sent each to the scalar
    `coarsest_order` and `fuse_period`, ~20 % of the kernel's time)."""
    mu, var, chi2, dof, amb = state[S_MU], state[S_VAR], state[S_CHI2], state[S_DOF], state[S_AMB]
    mu2, var2, flag, code = state[S_MU2], state[S_VAR2], state[S_FLAG], state[S_CODE]
    for j in range(m):
        u = us[j]
        var_k = sg[j] * sg[j]
        inv_total = 1.0 / (var[j] + var_k)
        d0 = mu[j] - cw[j]
        d0 -= np.rint(d0 * (1.0 / period)) * period
        gain = var[j] * inv_total
        half = 0.5 * period * period * inv_total
        tilt = d0 * period * inv_total
        teeth = (half + tilt < TOOTH_CUTOFF) | (half - tilt < TOOTH_CUTOFF)
        flag[j] = 1.0 if u and teeth else 0.0
        mu2[j] = mu[j] - d0 * gain if u else mu[j]
        var2[j] = gain * var_k if u else var[j]
        chi2[j] += d0 * d0 * inv_total if u else 0.0
        dof[j] += 1.0 if u else 0.0
    for j in range(m):
        if flag[j] != 0.0 and code[j] != 1.0:
            mu2[j], var2[j], _, amb_k = fuse_period(mu[j], var[j], cw[j], sg[j], period)
            amb[j] += amb_k * (1.0 - amb[j])
    for j in range(m):
        mu[j] = mu2[j]
        var[j] = var2[j]


drop_stale_kernels(globals())  # before any kernel runs: no machine code from older sources
