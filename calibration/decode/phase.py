"""Per-period least-squares cosine fit: wrapped position, modulation B* and its covariance.

Each pixel's samples of one period obey `v_i = C + alpha sin(psi_i) + beta cos(psi_i)`
with `alpha = -B sin(phi)`, `beta = B cos(phi)` (docs/physics.md section 1). With all steps
kept this is the classic closed form; with clipped steps excluded it is the least-squares
solution over the kept steps, solved per distinct exclusion pattern (a handful), not per pixel.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np

from calibration.decode.accumulate import SetSums
from calibration.decode.arrays import to_host

# Kept steps whose normal matrix is this ill-conditioned cannot fix a phase.
_MAX_CONDITION = 1e6
# The highest harmonic a fit on partial steps models (display gamma: ~30 % of the
# fundamental in harmonic 2, ~1 % in harmonic 3), whatever the noise mode.
PARTIAL_MAX_ORDER = 2


@dataclass
class _PartialFit:
    """Pixels of a chunk fitted on their kept steps only: what their noise covariance needs."""

    idx: Any  # (P,) positions in the chunk
    p: Any  # (P, k) fitted coefficients
    pattern: Any  # (P,) index into `gains`
    gains: Any  # (U, 2, steps) d(alpha, beta)/d v_i per exclusion pattern
    basis: Any  # (steps, k) design matrix


@dataclass
class SetFit:
    """Fit of one (axis, period) group over a chunk of pixels (1-D arrays)."""

    mean: Any  # C, DN
    level: Any  # level (DN) whose noise variance is the expected residual variance per dof
    alpha: Any
    beta: Any
    c_aa: Any  # covariance of (alpha, beta) per unit sample variance
    c_bb: Any
    c_ab: Any
    explained: Any  # p . rhs: the part of sum v^2 the fit explains (None unless asked)
    dof: Any  # kept samples - 3
    ok: Any  # enough kept samples, well-conditioned
    clipped: Any  # some steps were excluded as clipped
    low_clipped: Any  # a step below the fitted mean was excluded (clipped at the dark end)
    partial: _PartialFit | None = None  # the pixels fitted on a subset of steps

    @functools.cached_property
    def b2(self) -> Any:
        """Squared modulation alpha^2 + beta^2 (DN^2)."""
        return self.alpha**2 + self.beta**2

    @property
    def modulation(self) -> Any:
        """Observed modulation amplitude B* (DN)."""
        return self.b2**0.5

    @property
    def _isotropic(self) -> bool:
        """True when the covariance factors are the all-steps-kept scalars c I."""
        return isinstance(self.c_aa, float) and self.c_ab == 0.0 and self.c_aa == self.c_bb

    def modulation_var(self) -> Any:
        """Variance of B* per unit sample variance (linearized)."""
        if self._isotropic:
            return self.c_aa
        b2 = self.b2
        num = self.alpha**2 * self.c_aa + 2 * self.alpha * self.beta * self.c_ab
        num = num + self.beta**2 * self.c_bb
        isotropic = 0.5 * (self.c_aa + self.c_bb)
        return (num + isotropic * (b2 == 0)) / (b2 + (b2 == 0))

    def phase_var(self) -> Any:
        """Variance of the phase (rad^2) per unit sample variance (linearized)."""
        b2 = self.b2
        none = b2 == 0  # no modulation: no phase
        if self._isotropic:
            return self.c_aa / (b2 + none) + none * 1e30
        num = self.beta**2 * self.c_aa - 2 * self.alpha * self.beta * self.c_ab
        num = num + self.alpha**2 * self.c_bb
        b4 = b2 * b2
        none = b4 == 0  # also where float32 b2^2 underflows
        return num / (b4 + none) + none * 1e30

    def use_step_levels(self, xp: ModuleType, variance: Callable[[Any], Any], base: Any,
                        where: Any) -> None:
        """Give pixels fitted on kept steps each step's own noise variance (in place).

        With all steps kept the (alpha, beta) covariance is `var(C) (X^T X)^-1` exactly (the
        level's cosine is orthogonal to the products of the basis). With clipped steps the
        kept ones are the darker ones, so `var(C)` overstates their noise; here
        `sum_i var(mu_i) g_i g_i^T` (g_i: the step's gains) is stored divided by `base`,
        the variance the caller multiplies with, at the chunk pixels `where` is true for.
        """
        part = self.partial
        if part is None:
            return
        mu = part.p @ part.basis.T  # (P, steps) fitted value of every step
        var = variance(xp.maximum(mu, 0.0))
        gains = part.gains[part.pattern]  # (P, 2, steps)
        g_a, g_b = gains[:, 0, :], gains[:, 1, :]
        values = {
            "c_aa": (var * g_a * g_a).sum(axis=1),
            "c_bb": (var * g_b * g_b).sum(axis=1),
            "c_ab": (var * g_a * g_b).sum(axis=1),
        }
        b = base[part.idx]
        keep = where[part.idx] & (b > 0)
        safe = xp.where(keep, b, 1.0)
        for name, value in values.items():
            arr = getattr(self, name)
            arr[part.idx] = xp.where(keep, value / safe, arr[part.idx])

    def position(self, xp: ModuleType, period: float) -> Any:
        """Wrapped screen position in [0, period) screen px."""
        phi = xp.arctan2(-self.alpha, self.beta)
        return xp.mod(phi * (period / (2.0 * math.pi)), period)


class ExclusionPattern(NamedTuple):
    """Least-squares tables of one exclusion pattern (which steps were clipped)."""

    minv: np.ndarray  # (k, k) inverse normal matrix, zero rows/columns for dropped harmonics
    kept: int  # steps kept
    used: int  # columns fitted
    weights: np.ndarray  # (k,) residual weights sum_i (1 - h_ii) x_i over the kept steps
    gains: np.ndarray  # (2, steps) d(alpha, beta)/d v_i, zero for excluded steps


@functools.lru_cache(maxsize=64)
def design_matrix(steps: int, harmonics: tuple[int, ...]) -> np.ndarray:
    """(steps, k) design matrix: 1, sin(psi), cos(psi), then sin(k psi), cos(k psi) per harmonic.

    Public with `normal_inverse`: kernel_clipped.py builds its compiled tables from the same
    matrices, so both paths fit a clipped pixel alike."""
    psi = 2.0 * np.pi * np.arange(steps) / steps
    columns = [np.ones(steps)]
    for k in (1, *harmonics):
        columns += [np.sin(k * psi), np.cos(k * psi)]
    basis = np.stack(columns, axis=1)
    basis.setflags(write=False)  # cached and shared
    return basis


@functools.lru_cache(maxsize=4096)
def normal_inverse(steps: int, excluded_mask: int, harmonics: tuple[int, ...]) -> ExclusionPattern:
    """Least-squares tables of the kept steps of one exclusion pattern.

    Harmonics above `PARTIAL_MAX_ORDER` are not fitted on partial steps (residual-noise
    mode models harmonic 3 to keep it out of the noise estimate; with steps excluded it
    would also move the phase, and with the brightest 3 of 10 steps clipped it left no
    residual dof and 80-150x the fundamental's variance, which failed pixels that the
    same fit with the noise given decodes; the phase model is now the same in both
    modes). When too few steps are kept for all columns, the highest harmonics are
    dropped too (their rows and columns of the full-size inverse are zero); NaN when even
    the fundamental cannot be fitted. The residual weights `w` give
    `w . p = sum_i (1 - h_ii) mu_i` (h: the hat matrix, mu: fitted values): with noise
    variance linear in the level, the expected residual sum of squares is
    `offset * dof + slope * w . p`. Kept steps are unevenly
    weighted: when the bright ones clip, the dark ones carry most residual dof, so the kept
    samples' average level would overstate their noise. The gains let the (alpha, beta)
    covariance use each kept step's own noise variance. Cached: a pose has few patterns.
    """
    basis = design_matrix(steps, harmonics)
    kept = np.array([(excluded_mask >> i) & 1 == 0 for i in range(steps)])
    full = basis.shape[1]
    rows = basis[kept]
    n = int(rows.shape[0])
    widest = 3 + 2 * sum(1 for k in harmonics if k <= PARTIAL_MAX_ORDER) if excluded_mask else full
    for columns in range(widest, 2, -2):
        m = rows[:, :columns].T @ rows[:, :columns]
        if n >= columns and np.linalg.cond(m) <= _MAX_CONDITION:
            out = np.zeros((full, full))
            out[:columns, :columns] = np.linalg.inv(m)
            leverage = np.einsum("ij,jk,ik->i", rows, out, rows)
            gains = (out @ basis.T)[1:3] * kept
            return ExclusionPattern(out, n, columns, (1.0 - leverage) @ rows, gains)
    nan = np.full((full, full), np.nan)
    return ExclusionPattern(nan, n, full, np.zeros(full), np.zeros((2, steps)))


def fit_set(xp: ModuleType, sums: SetSums, sl: slice, *, residuals: bool = False,
            skip: Any = None) -> SetFit:
    """Fit the cosine model of one period group on the flattened pixel range `sl`.

    The model also includes the set's extra harmonics (`harmonic_orders`): with all steps
    kept they are orthogonal to the fundamental (phase unchanged), but they keep display
    gamma out of the residual noise and, with clipped steps excluded, out of the phase.
    Results are float32 (the sums are float32); `residuals` also computes, in float64,
    the part of `sum v^2` the fit explains (the residual is a small difference of large
    sums). The covariance factors are scalars unless some pixel has clipped steps.
    `skip` (bool per chunk pixel) marks pixels that cannot be valid whatever their fit
    (they see no screen): with clipped steps they get no least-squares fit, like pixels
    whose every step clipped.
    """
    n = sums.layout.steps
    count = 3 + len(sums.extra)
    s0, a, b = (x.reshape(-1)[sl] for x in (sums.s0, sums.a, sums.b))
    size = a.shape[0]
    explained = None
    if residuals:
        wide = [x.reshape(-1)[sl].astype(xp.float64) for x in (sums.a, sums.b, *sums.extra)]
        explained = s0.astype(xp.float64) ** 2 / n
        for extra in wide:
            explained = explained + extra**2 * (2.0 / n)
    scale = xp.float32(2.0 / n)
    fit = SetFit(
        mean=s0 * xp.float32(1.0 / n),
        level=s0 * xp.float32(1.0 / n),
        alpha=a * scale,
        beta=b * scale,
        c_aa=2.0 / n,
        c_bb=2.0 / n,
        c_ab=0.0,
        explained=explained,
        dof=xp.full(size, float(n - count), dtype=xp.float32),
        ok=xp.ones(size, dtype=bool),
        clipped=xp.zeros(size, dtype=bool),
        low_clipped=xp.zeros(size, dtype=bool),
    )
    if sums.excluded is None:
        return fit
    bits = sums.excluded.reshape(-1)[sl]
    every = (1 << n) - 1
    # every step clipped (e.g. a black border), or clipped and seeing no screen: no fit
    dead = bits == every
    if skip is not None:
        dead = dead | ((bits != 0) & skip)
    dead = xp.nonzero(dead)[0]
    if dead.shape[0]:
        for arr in (fit.mean, fit.level, fit.alpha, fit.beta, fit.dof):
            arr[dead] = 0.0
        if explained is not None:
            explained[dead] = 0.0
        fit.ok[dead] = False
        fit.clipped[dead] = True
    partial = (bits != 0) & (bits != every)
    idx = xp.nonzero(partial & ~skip if skip is not None else partial)[0]
    if idx.shape[0] == 0:
        return fit
    uniq, inv = xp.unique(bits[idx], return_inverse=True)
    tables = [normal_inverse(n, int(u), sums.harmonics) for u in to_host(uniq)]
    inv = inv.reshape(-1)
    minv = xp.asarray(np.stack([t.minv for t in tables]))[inv]  # (P, k, k)
    counts = np.array([(t.kept, t.used) for t in tables], dtype=np.float64)
    weights = xp.asarray(np.stack([t.weights for t in tables]))[inv]  # (P, k)
    kept, used = (xp.asarray(c)[inv] for c in counts.T)
    rhs = xp.stack(
        [x.reshape(-1)[sl][idx].astype(xp.float64) for x in (sums.s0, sums.a, sums.b, *sums.extra)],
        axis=1,
    )
    p = xp.einsum("pij,pj->pi", minv, rhs)
    good = xp.isfinite(p).all(axis=1)
    p = xp.where(good[:, None], p, 0.0)
    fit.mean[idx] = p[:, 0]
    fit.level[idx] = (weights * p).sum(axis=1) / xp.maximum(kept - used, 1.0)
    fit.alpha[idx] = p[:, 1]
    fit.beta[idx] = p[:, 2]
    for name, (i, j) in (("c_aa", (1, 1)), ("c_bb", (2, 2)), ("c_ab", (1, 2))):
        arr = xp.full(size, getattr(fit, name), dtype=xp.float32)
        arr[idx] = xp.where(good, minv[:, i, j], 0.0)
        setattr(fit, name, arr)
    if explained is not None:
        explained[idx] = (p * rhs).sum(axis=1)
    fit.dof[idx] = xp.maximum(kept - used, 0.0)
    fit.ok[idx] = good
    fit.clipped[idx] = True
    basis = design_matrix(n, sums.harmonics)
    excluded = xp.asarray((to_host(uniq)[:, None] >> np.arange(n)) & 1 == 1)[inv]  # (P, n)
    fit.low_clipped[idx] = (excluded & (p @ basis.T.astype(np.float64) < p[:, :1])).any(axis=1)
    gains = xp.asarray(np.stack([t.gains for t in tables]))
    fitted = xp.nonzero(good)[0]  # pixels without a fit keep no covariance to refine
    fit.partial = _PartialFit(idx[fitted], p[fitted], inv[fitted], gains, xp.asarray(basis))
    return fit
