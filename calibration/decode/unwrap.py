"""Multi-period Bayesian unwrapping: product of per-period likelihood combs with a screen prior.

Periods are fused coarsest first (docs/physics.md section 3). The coarsest period's comb times
the uniform prior on the screen extent picks its order; each finer period's comb
multiplies the current Gaussian posterior N(mu, s^2): the candidate orders m give
components with weights exp(-d_m^2 / 2(s^2 + sigma_k^2)). Components whose centres are
not separated from the best one (within `_MERGE_SIGMA` posterior sigmas) are merged by
moment matching (the comb is then too wide to matter); the mass on separated components is
the ambiguity, the chance that the chosen peak is the wrong one. The innovation
chi-square `sum d^2 / (s^2 + sigma_k^2)` measures whether the periods agree.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Any

from calibration.decode.arrays import special

# Coarsest-period candidates further than this many sigmas from the screen ends have
# Gaussian masses of exactly 0 or 1 to < 1e-17: no need to evaluate them.
_FAR_SIGMA = 8.5
# Components closer than this many posterior sigmas form one peak.
_MERGE_SIGMA = 2.0
# Finer periods: the nearest tooth and its two neighbours are weighed. Where a tooth two
# away would still carry weight, the neighbours already carry far more than any ambiguity
# limit (or the comb is too wide to matter and all merge into one peak).


@dataclass
class AxisPosterior:
    """Fused position of one axis for a chunk of pixels (1-D arrays)."""

    position: Any  # screen px
    sigma: Any  # screen px
    ambiguity: Any  # posterior mass on competing peaks
    chi2: Any  # innovation chi-square of the fusion
    dof: Any  # number of fused finer periods


def _coarsest(xp: ModuleType, c: Any, sigma: Any, period: float, lo: float, hi: float):
    """Order of the coarsest period under a uniform prior on [lo, hi]: (mu, ambiguity).

    The period exceeds the extent, so at most one candidate lies inside. Pixels whose
    candidates are all further than `_FAR_SIGMA` sigmas from both ends get it (or the
    least-outside one) with zero ambiguity; only the others evaluate the Gaussian masses.
    """
    c = c.astype(xp.float64)
    # How far inside [lo, hi] each candidate c - period, c, c + period lies (< 0: outside).
    in_lo = xp.minimum(hi - c + period, c - period - lo)
    in_0 = xp.minimum(hi - c, c - lo)
    in_hi = xp.minimum(hi - c - period, c + period - lo)
    mu = xp.where(in_0 >= in_lo, c, c - period)
    mu = xp.where(in_hi > xp.maximum(in_0, in_lo), c + period, mu)
    ambiguity = xp.zeros(c.shape, dtype=sigma.dtype)
    reach = _FAR_SIGMA * sigma
    near = (xp.abs(in_lo) < reach) | (xp.abs(in_0) < reach) | (xp.abs(in_hi) < reach)
    near = xp.nonzero(near)[0]
    if near.shape[0] == 0:
        return mu, ambiguity
    ndtr = special(xp).ndtr
    sub = c[near][None, :] + period * xp.asarray([-1.0, 0.0, 1.0])[:, None]
    s = sigma[near]
    mass = ndtr((hi - sub) / s) - ndtr((lo - sub) / s)
    top_i = xp.argmax(mass, axis=0)
    mu[near] = xp.take_along_axis(sub, top_i[None, :], axis=0)[0]
    top = xp.take_along_axis(mass, top_i[None, :], axis=0)[0]
    total = mass.sum(axis=0)
    ambiguity[near] = xp.where(total > 0, 1.0 - top / xp.where(total > 0, total, 1.0), 1.0)
    return mu, ambiguity


def fuse_axis(
    xp: ModuleType,
    positions: list[Any],
    sigmas: list[Any],
    periods: list[float],
    usable: list[Any],
    extent_px: int,
) -> AxisPosterior:
    """Fuse wrapped positions (coarsest first) into one position and sigma per pixel.

    The position stays float64 (screen px to ~1e-4 px over a few thousand px); variances,
    weights and chi-squares follow the sigmas' dtype (float32 from the decoder).
    """
    lo, hi = -0.5, extent_px - 0.5
    mu, ambiguity = _coarsest(xp, positions[0], sigmas[0], periods[0], lo, hi)
    var = sigmas[0] ** 2
    chi2 = xp.zeros_like(var)
    dof = xp.zeros_like(var)
    for c, sig, period, use in zip(positions[1:], sigmas[1:], periods[1:], usable[1:], strict=True):
        var_k = sig * sig
        inv_total = 1.0 / (var + var_k)
        wide = mu - c
        wide -= xp.rint(wide * (1.0 / period)) * period  # offset to the nearest tooth
        d0 = wide.astype(var.dtype)
        gain = var * inv_total
        post_var = gain * var_k
        # Neighbouring teeth (orders -1, +1): weights relative to the nearest one. Their
        # posterior centres sit `step` = period*gain away: separated peaks, or one merged peak.
        half = (0.5 * period * period) * inv_total
        tilt = (d0 * period) * inv_total
        w_lo = xp.exp(-(half + tilt))
        w_hi = xp.exp(tilt - half)
        step = period * gain
        separated = step * step > (_MERGE_SIGMA * _MERGE_SIGMA) * post_var
        amb_k = xp.where(separated, (w_lo + w_hi) / (1.0 + w_lo + w_hi), 0.0)
        new_mu = mu - d0 * gain
        new_var = post_var
        merged = xp.nonzero(~separated & use)[0]
        if merged.shape[0]:  # one merged peak: moment-match the three components
            lo_m, hi_m, st = w_lo[merged], w_hi[merged], step[merged]
            norm = 1.0 + lo_m + hi_m
            shift = (hi_m - lo_m) * st / norm
            spread = (lo_m * (st + shift) ** 2 + hi_m * (st - shift) ** 2 + shift**2) / norm
            new_mu[merged] += shift
            new_var[merged] += spread
        # Unusable periods (few pixels) leave their pixels' state unchanged.
        skip = xp.nonzero(~use)[0]
        innovation = d0 * d0 * inv_total
        innovation[skip] = 0.0
        amb_k[skip] = 0.0
        new_mu[skip] = mu[skip]
        new_var[skip] = var[skip]
        chi2 += innovation
        dof += use
        ambiguity += amb_k * (1.0 - ambiguity)
        mu, var = new_mu, new_var
    return AxisPosterior(mu, xp.sqrt(var), ambiguity, chi2, dof)
