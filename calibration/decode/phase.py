"""Per-period least-squares cosine fit: wrapped position, modulation B* and its covariance.

Each pixel's samples of one period obey `v_i = C + alpha sin(psi_i) + beta cos(psi_i)`
with `alpha = -B sin(phi)`, `beta = B cos(phi)` (PHYSICS.md section 1). With all steps
kept this is the classic closed form; with clipped steps excluded it is the least-squares
solution over the kept steps, solved per distinct exclusion pattern (a handful), not per pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

from calibration.decode.accumulate import SetSums
from calibration.decode.arrays import to_host

# Kept steps whose normal matrix is this ill-conditioned cannot fix a phase.
_MAX_CONDITION = 1e6


@dataclass
class SetFit:
    """Fit of one (axis, period) group over a chunk of pixels (1-D arrays)."""

    mean: Any  # C, DN
    level: Any  # average of the kept samples (DN): where their noise is evaluated
    alpha: Any
    beta: Any
    c_aa: Any  # covariance of (alpha, beta) per unit sample variance
    c_bb: Any
    c_ab: Any
    explained: Any  # p . rhs: the part of sum v^2 the fit explains
    dof: Any  # kept samples - 3
    ok: Any  # enough kept samples, well-conditioned
    clipped: Any  # some steps were excluded as clipped

    @property
    def modulation(self) -> Any:
        """Observed modulation amplitude B* (DN)."""
        return (self.alpha**2 + self.beta**2) ** 0.5

    def modulation_var(self) -> Any:
        """Variance of B* per unit sample variance (linearized)."""
        b2 = self.alpha**2 + self.beta**2
        num = self.alpha**2 * self.c_aa + 2 * self.alpha * self.beta * self.c_ab
        num = num + self.beta**2 * self.c_bb
        isotropic = 0.5 * (self.c_aa + self.c_bb)
        return (num + isotropic * (b2 == 0)) / (b2 + (b2 == 0))

    def phase_var(self) -> Any:
        """Variance of the phase (rad^2) per unit sample variance (linearized)."""
        b2 = self.alpha**2 + self.beta**2
        num = self.beta**2 * self.c_aa - 2 * self.alpha * self.beta * self.c_ab
        num = num + self.alpha**2 * self.c_bb
        return num / (b2 * b2 + (b2 == 0)) + (b2 == 0) * 1e30  # no modulation: no phase

    def position(self, xp: ModuleType, period: float) -> Any:
        """Wrapped screen position in [0, period) screen px."""
        phi = xp.arctan2(-self.alpha, self.beta)
        return xp.mod(phi * (period / (2.0 * math.pi)), period)


def _normal_inverse(
    steps: int, excluded_mask: int, harmonics: tuple[int, ...]
) -> tuple[np.ndarray, int, int]:
    """Inverse normal matrix of the kept steps, their count and the columns used.

    Columns: 1, sin(psi), cos(psi), then sin(k psi), cos(k psi) for each extra harmonic k.
    When too few steps are kept for all of them, the highest harmonics are dropped (their
    rows and columns of the returned, full-size matrix are zero); NaN when even the
    fundamental cannot be fitted.
    """
    psi = 2.0 * np.pi * np.arange(steps) / steps
    kept = np.array([(excluded_mask >> i) & 1 == 0 for i in range(steps)])
    basis = [np.ones(steps)]
    for k in (1, *harmonics):
        basis += [np.sin(k * psi), np.cos(k * psi)]
    full = len(basis)
    rows = np.stack(basis, axis=1)[kept]
    n = int(rows.shape[0])
    for columns in range(full, 2, -2):
        m = rows[:, :columns].T @ rows[:, :columns]
        if n >= columns and np.linalg.cond(m) <= _MAX_CONDITION:
            out = np.zeros((full, full))
            out[:columns, :columns] = np.linalg.inv(m)
            return out, n, columns
    return np.full((full, full), np.nan), n, full


def fit_set(xp: ModuleType, sums: SetSums, sl: slice) -> SetFit:
    """Fit the cosine model of one period group on the flattened pixel range `sl`.

    The model also includes the set's extra harmonics (`harmonic_orders`): with all steps
    kept they are orthogonal to the fundamental (phase unchanged), but they keep display
    gamma out of the residual noise and, with clipped steps excluded, out of the phase.
    """
    n = sums.layout.steps
    flat = [x.reshape(-1)[sl].astype(xp.float64) for x in (sums.s0, sums.a, sums.b)]
    flat += [x.reshape(-1)[sl].astype(xp.float64) for x in sums.extra]
    s0, a, b = flat[:3]
    size = a.shape[0]
    full = xp.full(size, 2.0 / n)
    explained = s0**2 / n
    for extra in flat[1:]:
        explained = explained + extra**2 * (2.0 / n)
    fit = SetFit(
        mean=s0 / n,
        level=s0 / n,
        alpha=a * (2.0 / n),
        beta=b * (2.0 / n),
        c_aa=full,
        c_bb=full.copy(),
        c_ab=xp.zeros(size),
        explained=explained,
        dof=xp.full(size, float(n - len(flat))),
        ok=xp.ones(size, dtype=bool),
        clipped=xp.zeros(size, dtype=bool),
    )
    if sums.excluded is None:
        return fit
    bits = sums.excluded.reshape(-1)[sl]
    idx = xp.nonzero(bits)[0]
    if idx.shape[0] == 0:
        return fit
    uniq, inv = xp.unique(bits[idx], return_inverse=True)
    tables = [_normal_inverse(n, int(u), sums.harmonics) for u in to_host(uniq)]
    minv = xp.asarray(np.stack([t[0] for t in tables]))[inv.reshape(-1)]  # (P, k, k)
    counts = np.array([(t[1], t[2]) for t in tables], dtype=np.float64)
    kept, used = (xp.asarray(c)[inv.reshape(-1)] for c in counts.T)
    rhs = xp.stack([f[idx] for f in flat], axis=1)
    p = xp.einsum("pij,pj->pi", minv, rhs)
    good = xp.isfinite(p).all(axis=1)
    p = xp.where(good[:, None], p, 0.0)
    fit.mean[idx] = p[:, 0]
    fit.level[idx] = s0[idx] / xp.maximum(kept, 1.0)
    fit.alpha[idx] = p[:, 1]
    fit.beta[idx] = p[:, 2]
    fit.c_aa[idx] = xp.where(good, minv[:, 1, 1], 0.0)
    fit.c_bb[idx] = xp.where(good, minv[:, 2, 2], 0.0)
    fit.c_ab[idx] = xp.where(good, minv[:, 1, 2], 0.0)
    fit.explained[idx] = (p * rhs).sum(axis=1)
    fit.dof[idx] = xp.maximum(kept - used, 0.0)
    fit.ok[idx] = good
    fit.clipped[idx] = True
    return fit
