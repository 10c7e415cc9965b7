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
# Candidate orders around the nearest one (finer periods). Where an order two away would
# still carry weight, the adjacent ones already carry far more than any ambiguity limit.
_NEIGHBOURS = (-1, 0, 1)


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
    offsets = xp.asarray(_NEIGHBOURS, dtype=mu.dtype)[:, None]
    centre = _NEIGHBOURS.index(0)
    for c, sig, period, use in zip(positions[1:], sigmas[1:], periods[1:], usable[1:], strict=True):
        var_k = sig**2
        total = var + var_k
        m0 = xp.rint((mu - c) / period)
        d = mu[None, :] - (c[None, :] + (m0[None, :] + offsets) * period)  # (J, P)
        logw = -0.5 * d**2 / total
        w = xp.exp(logw - logw[centre])
        gain = var / total
        centres = mu[None, :] - d * gain
        post_var = var * var_k / total
        separated = xp.abs(centres - centres[centre]) > _MERGE_SIGMA * xp.sqrt(post_var)
        near = xp.where(separated, 0.0, w)
        amb_k = xp.where(separated, w, 0.0).sum(axis=0) / w.sum(axis=0)
        norm = near.sum(axis=0)
        new_mu = (near * centres).sum(axis=0) / norm
        new_var = post_var + (near * (centres - new_mu) ** 2).sum(axis=0) / norm
        chi2 = xp.where(use, chi2 + d[centre] ** 2 / total, chi2)
        dof = xp.where(use, dof + 1.0, dof)
        ambiguity = xp.where(use, ambiguity + amb_k - ambiguity * amb_k, ambiguity)
        mu = xp.where(use, new_mu, mu)
        var = xp.where(use, new_var, var)
    return AxisPosterior(mu, xp.sqrt(var), ambiguity, chi2, dof)
