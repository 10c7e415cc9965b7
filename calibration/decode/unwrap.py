"""Multi-period Bayesian unwrapping: product of per-period likelihood combs with a screen prior.

Periods are fused coarsest first (PHYSICS.md section 2). The coarsest period's comb times
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
    """Order of the coarsest period under a uniform prior on [lo, hi]: (mu, ambiguity)."""
    ndtr = special(xp).ndtr
    cand = c[None, :] + period * xp.asarray([-1.0, 0.0, 1.0])[:, None]
    mass = ndtr((hi - cand) / sigma) - ndtr((lo - cand) / sigma)
    best = xp.argmax(mass, axis=0)
    mu = xp.take_along_axis(cand, best[None, :], axis=0)[0]
    top = xp.take_along_axis(mass, best[None, :], axis=0)[0]
    total = mass.sum(axis=0)
    ambiguity = xp.where(total > 0, 1.0 - top / xp.where(total > 0, total, 1.0), 1.0)
    return mu, ambiguity


def fuse_axis(
    xp: ModuleType,
    positions: list[Any],
    sigmas: list[Any],
    periods: list[float],
    usable: list[Any],
    extent_px: int,
) -> AxisPosterior:
    """Fuse wrapped positions (coarsest first) into one position and sigma per pixel."""
    lo, hi = -0.5, extent_px - 0.5
    mu, ambiguity = _coarsest(xp, positions[0], sigmas[0], periods[0], lo, hi)
    var = sigmas[0] ** 2
    chi2 = xp.zeros_like(mu)
    dof = xp.zeros_like(mu)
    for c, sig, period, use in zip(positions[1:], sigmas[1:], periods[1:], usable[1:], strict=True):
        var_k = sig**2
        total = var + var_k
        d0 = mu - c - xp.rint((mu - c) / period) * period  # offset to the nearest tooth
        gain = var / total
        post_var = var * var_k / total
        # Neighbouring teeth (orders -1, +1): weights relative to the nearest one. Their
        # posterior centres sit period*gain away: separated peaks, or one merged peak.
        w_lo = xp.exp(-(period * period + 2.0 * d0 * period) / (2.0 * total))
        w_hi = xp.exp(-(period * period - 2.0 * d0 * period) / (2.0 * total))
        norm = 1.0 + w_lo + w_hi
        separated = period * gain > _MERGE_SIGMA * xp.sqrt(post_var)
        amb_k = xp.where(separated, (w_lo + w_hi) / norm, 0.0)
        step = period * gain  # posterior centres of teeth -1, +1 sit -step, +step from tooth 0
        shift = (w_hi - w_lo) * step / norm
        spread = (w_lo * (step + shift) ** 2 + w_hi * (step - shift) ** 2 + shift**2) / norm
        new_mu = mu - d0 * gain + xp.where(separated, 0.0, shift)
        new_var = post_var + xp.where(separated, 0.0, spread)
        chi2 = xp.where(use, chi2 + d0**2 / total, chi2)
        dof = xp.where(use, dof + 1.0, dof)
        ambiguity = xp.where(use, ambiguity + amb_k - ambiguity * amb_k, ambiguity)
        mu = xp.where(use, new_mu, mu)
        var = xp.where(use, new_var, var)
    return AxisPosterior(mu, xp.sqrt(var), ambiguity, chi2, dof)
