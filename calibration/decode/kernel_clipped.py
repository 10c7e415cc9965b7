"""Compiled fits of pixels with clipped steps (numba), for kernel_sums.py's block loops.

phase.py `fit_set` over a block of pixels: the closed form for every pixel, then, for the
pixels with some steps clipped, the least squares over their kept steps (the tables of
each exclusion pattern from `normal_inverse`, gathered into `PatternTables`: one row per
pattern, looked up per pixel); with them the decoder's residuals (`_residuals`) and the
numerators of `SetFit.use_step_levels`. The rest of the finish (variances, sigmas, phases,
unwrapping) then runs in the same vectorized loops as for unclipped pixels. Float32
rounding where the array path keeps float32 arrays.

Per pixel the fit reads only the columns partial fits model (`PatternTables.widths`: the
set's harmonic 3 rows are zero in every pattern's inverse). The noise covariance of a fit
on kept steps (`use_step_levels`: each step's variance from the noise line at its fitted
value) comes from the pattern's summed tables, the line being linear above a threshold,
plus a correction for the few steps fitted below it (a pixel's darkest steps near the
black level): a sum over every step cost as much as the rest of the fit.
"""

from __future__ import annotations

import functools
import math
import threading

import numpy as np
from numba import njit

from calibration.decode.accumulate import SetSums
from calibration.decode.kernel_cache import drop_stale_kernels
from calibration.decode.kernel_sets import explained, line_var, nyquist
from calibration.decode.phase import PARTIAL_MAX_ORDER, design_matrix, normal_inverse

MAX_TABLE_STEPS = 16  # dense pattern index per set: 2^steps entries (steps above: array path)
# Rows of `PatternTables.rows`, per set and pattern (F: the widest set's columns, T: its
# steps): minv (F x F), residual weights (F), the gains' products g g^T per step (3 x T:
# aa, bb, ab; zero at clipped steps and past the set's), sum_i g g^T (3), sum_i x_im g g^T
# (3 x F), kept and used steps.


class PatternTables:
    """Least-squares tables of the exclusion patterns met so far, per set: `index[k, mask]`
    is the row of `rows` (-1: not built yet, layout above). `basis[k]`: the (T, F) design;
    `widths[k]`: the columns a fit on partial steps can use (`partial_width`)."""

    def __init__(self, sets: list[SetSums]) -> None:
        self.sets = sets
        self.width = max(s.rows for s in sets)
        self.steps = max(s.layout.steps for s in sets)
        # (index, rows) replaced as one tuple: a thread never pairs a new index with old rows
        self._pair = (np.full((len(sets), 1 << self.steps), -1, dtype=np.int64),
                      np.zeros((0, self.row_size), dtype=np.float64))
        self.basis = np.zeros((len(sets), self.steps, self.width))
        for k, s in enumerate(sets):
            b = design_matrix(s.layout.steps, s.harmonics)
            self.basis[k, :b.shape[0], :b.shape[1]] = b
        self.set_steps = np.array([s.layout.steps for s in sets], dtype=np.int64)
        self.widths = np.array([partial_width(s) for s in sets], dtype=np.int64)
        self._lock = threading.Lock()

    @property
    def row_size(self) -> int:
        """Values per table row."""
        return self.width * self.width + self.width + 3 * self.steps + 3 + 3 * self.width + 2

    def kernel_tables(self, bits: np.ndarray, c0: int, n: int) -> tuple[np.ndarray, ...]:
        """The kernels' `tables` argument for columns c0..c0+n of `bits`: (index, rows,
        basis, widths)."""
        return (*self.tables(bits, c0, n), self.basis, self.widths)

    def tables(self, bits: np.ndarray, c0: int, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(index, rows) covering every pattern of columns c0..c0+n of `bits` (built as
        needed; a consistent pair that later growth does not change)."""
        pair = self._pair
        if bits.shape[0] == 0:
            return pair
        unknown = unknown_patterns(bits, c0, n, pair[0], self.set_steps)
        if unknown.shape[0] == 0:
            return pair
        with self._lock:
            index, rows = self._pair[0].copy(), [self._pair[1]]
            count = rows[0].shape[0]
            for k, mask in unknown.tolist():
                if index[k, mask] >= 0:
                    continue  # built meanwhile by another thread
                s = self.sets[k]
                rows.append(_pattern_row(s.layout.steps, mask, s.harmonics, self.width,
                                         self.steps)[None])
                index[k, mask] = count
                count += 1
            self._pair = (index, np.concatenate(rows))
            return self._pair


def partial_width(sums: SetSums) -> int:
    """Columns of a set's fits on partial steps: the level, the fundamental and the harmonics
    up to `PARTIAL_MAX_ORDER` (`normal_inverse`: the others' rows and columns are zero)."""
    return 3 + 2 * sum(1 for h in sums.harmonics if h <= PARTIAL_MAX_ORDER)


@functools.lru_cache(maxsize=8192)
def _pattern_row(steps: int, mask: int, harmonics: tuple[int, ...], width: int,
                 t_max: int) -> np.ndarray:
    """One row of `PatternTables.rows` (layout above; read-only), kept for the process: a
    service decodes pose after pose with one plan and meets the same patterns again."""
    pat = normal_inverse(steps, mask, harmonics)
    b = design_matrix(steps, harmonics)
    basis = np.zeros((steps, width))
    basis[:, :b.shape[1]] = b
    f, t, w = width, t_max, pat.minv.shape[0]
    row = np.zeros(f * f + f + 3 * t + 3 + 3 * f + 2)
    minv = np.zeros((f, f))
    minv[:w, :w] = pat.minv
    ga, gb = pat.gains
    prods = np.zeros((3, t))
    prods[:, :steps] = ga * ga, gb * gb, ga * gb
    row[:f * f] = minv.ravel()
    row[f * f:f * f + w] = pat.weights
    g0 = f * f + f
    row[g0:g0 + 3 * t] = prods.ravel()
    row[g0 + 3 * t:g0 + 3 * t + 3 + 3 * f] = _covariance_terms(prods[:, :steps], basis, f)
    row[-2:] = pat.kept, pat.used
    row.flags.writeable = False
    return row


def _covariance_terms(prods: np.ndarray, basis: np.ndarray, width: int) -> np.ndarray:
    """sum_i g_i g_i^T and sum_i x_im g_i g_i^T (m < width) as (aa, bb, ab) triples from the
    gains' products per step `prods` (3, T): with variance linear in the fitted step values
    mu_i = x_i . p, `use_step_levels`'s sum_i var(mu_i) g_i g_i^T is
    `c0 S + slope sum_m p_m T_m`."""
    terms = np.zeros((1 + width, 3))
    terms[0] = prods.sum(axis=1)
    terms[1:1 + basis.shape[1]] = basis.T @ prods.T
    return terms.ravel()


def pattern_tables(sets: list[SetSums]) -> PatternTables | None:
    """New pattern tables of a plan's sets (its decoder keeps them: the patterns met grow
    with its ranges), None for plans of > 16 steps (the array path fits those)."""
    if max(s.layout.steps for s in sets) > MAX_TABLE_STEPS:
        return None
    return PatternTables(sets)


def no_tables() -> tuple[np.ndarray, ...]:
    """The kernels' `tables` argument where no pixel is fitted on partial steps (plans of
    > 16 steps, ranges without clipped steps): empty arrays of `kernel_tables`' types."""
    return (np.zeros((0, 1), np.int64), np.zeros((0, 1)), np.zeros((0, 1, 1)),
            np.zeros(0, np.int64))


@njit(cache=True, error_model="numpy", nogil=True)
def unknown_patterns(bits, c0, n, index, steps):
    """The distinct partial patterns of columns c0..c0+n of `bits` without a table row:
    (count, 2) int64 rows (set, mask), in order of appearance (one pass, no sort)."""
    seen = np.zeros(index.shape, dtype=np.bool_)
    out = np.empty((index.shape[0] * index.shape[1], 2), dtype=np.int64)
    count = 0
    for k in range(bits.shape[0]):
        row, known, every = bits[k], index[k], (1 << steps[k]) - 1
        for j in range(c0, c0 + n):
            q = row[j]
            if q != 0 and q != every and known[q] < 0 and not seen[k, q]:
                seen[k, q] = True
                out[count, 0] = k
                out[count, 1] = q
                count += 1
    return out[:count]


@njit(cache=True, error_model="numpy", inline="always")
def _table_fits(sums, bits, k, j0, m, r0, nrow, fw, n, rows, index, basis, p, residual,
                want_low, cov, lin, line, skip, fits, fitted, partial, covs, expl, dofk, levk,
                low):
    """phase.fit_set of set k for the block pixels 0..m (columns j0..) with some steps
    clipped, each from its pattern's row of the tables (kept steps only), written over
    `fit_block`'s closed form: mean, alpha, beta, fitted, c_aa, c_bb, c_ab; the
    use_step_levels numerators (with `cov`, in `covs[3..5, k]`; `partial` where fitted);
    with `residual` the explained sum, dof and level (`expl`, `dofk`, `levk`); with
    `want_low` a step clipped at the dark end (or-ed into `low`). Pixels with every step
    clipped, or `skip`, get no fit. `fw`: the columns partial fits use (the others'
    coefficients are zero, left unwritten in `p`, (F,) scratch); `lin`: (c0, slope,
    threshold) of `line` as c0 + slope * max(mu, threshold) for a step value mu (a finite
    threshold), or c0 + slope * mu where every fitted step value exceeds it. One loop over
    the pixels, not a call per pixel: the arrays a per-pixel call binds cost reference
    counting (numba) that was ~3x the fit's arithmetic."""
    f32 = np.float32
    width, t_max = basis.shape[1], basis.shape[0]
    size = rows.shape[1]
    every = (1 << n) - 1
    alpha, beta, mean = fits[0, k], fits[1, k], fits[2, k]
    g0 = width * width + width  # the gains' products in a table row
    cv = g0 + 3 * t_max  # the summed covariance terms
    # alpha, beta and the mean need 3 rows of the table's inverse; the harmonics' rows
    # only for the residuals, the dark-end test or a noise line that is not one constant
    # over every step value (else they are left 0)
    need = fw if residual or want_low or (cov and (lin[1] != 0.0 or lin[2] > -math.inf)) else 3
    for j in range(m):
        q = bits[k, j0 + j]
        if q == 0:
            continue
        if q == every or skip[j]:  # every step clipped, or no screen seen: no fit
            mean[j] = alpha[j] = beta[j] = 0.0
            fitted[k, j] = False
            expl[j] = dofk[j] = levk[j] = 0.0
            continue
        t, jc = index[k, q], j0 + j
        # each p_i is finite exactly when every sum is (finite tables, float64 headroom)
        good = True
        for mm in range(nrow):
            good = good and math.isfinite(sums[r0 + mm, jc])
        for i in range(fw):
            acc = 0.0
            for mm in range(fw if i < need else 0):
                acc += rows[t, i * width + mm] * float(sums[r0 + mm, jc])
            p[i] = acc if good else 0.0
        kept, used = rows[t, size - 2], rows[t, size - 1]
        lev = 0.0
        e = 0.0
        for i in range(fw if residual else 0):
            lev += rows[t, width * width + i] * p[i]
            e += p[i] * float(sums[r0 + i, jc])
        lw = False
        if want_low:
            for i in range(min(n, t_max)):
                if (q >> i) & 1:
                    v = 0.0
                    for mm in range(fw):
                        v += p[mm] * basis[i, mm]
                    lw = lw or v < p[0]
        naa = nbb = nab = 0.0
        if cov and good:
            c0, slope, threshold = lin[0], lin[1], lin[2]
            bound = p[0]  # a lower bound of every step's fitted value (none needed: -inf)
            for h in range(1, fw - 1 if threshold > -math.inf else 1, 2):
                bound -= math.sqrt(p[h] * p[h] + p[h + 1] * p[h + 1])
            if bound > threshold or math.isfinite(threshold):
                # the line is linear over the steps (c0 + slope mu): the tables' sums ...
                naa, nbb, nab = c0 * rows[t, cv], c0 * rows[t, cv + 1], c0 * rows[t, cv + 2]
                for mm in range(fw):
                    w = slope * p[mm]
                    naa += w * rows[t, cv + 3 + 3 * mm]
                    nbb += w * rows[t, cv + 4 + 3 * mm]
                    nab += w * rows[t, cv + 5 + 3 * mm]
                for i in range(n if bound <= threshold else 0):
                    # ... and for the steps fitted below the threshold, where the line is
                    # its constant c0 + slope threshold, the difference
                    v = 0.0
                    for mm in range(fw):
                        v += p[mm] * basis[i, mm]
                    if v < threshold:
                        d = slope * (threshold - v)
                        naa += d * rows[t, g0 + i]
                        nbb += d * rows[t, g0 + t_max + i]
                        nab += d * rows[t, g0 + 2 * t_max + i]
            else:  # a line that is not increasing: each kept step's own variance
                for i in range(n):
                    v = 0.0
                    for mm in range(fw):
                        v += p[mm] * basis[i, mm]
                    vi = line_var(line, max(v, 0.0))
                    naa += vi * rows[t, g0 + i]
                    nbb += vi * rows[t, g0 + t_max + i]
                    nab += vi * rows[t, g0 + 2 * t_max + i]
        mean[j], alpha[j], beta[j] = f32(p[0]), f32(p[1]), f32(p[2])
        levk[j] = f32(lev / max(kept - used, 1.0))
        covs[0, k, j] = float(f32(rows[t, width + 1])) if good else 0.0
        covs[1, k, j] = float(f32(rows[t, 2 * width + 2])) if good else 0.0
        covs[2, k, j] = float(f32(rows[t, width + 2])) if good else 0.0
        expl[j], dofk[j] = e, float(f32(max(kept - used, 0.0)))
        covs[3, k, j], covs[4, k, j], covs[5, k, j] = naa, nbb, nab
        fitted[k, j] = good
        partial[k, j] = good and cov
        low[j] = low[j] or lw


@njit(cache=True, error_model="numpy", inline="always")
def _table_fits_n(sums, bits, k, j0, m, r0, nrow, fw, n, rows, index, basis, p,
                  residual, want_low, cov, lin, line, skip, fits, fitted, partial, covs, expl,
                  dofk, levk, low):
    """`_table_fits` with the set's row count and partial fits' columns constants for the
    common layouts (3 + 2 harmonics: 5 or 7 rows, 5 columns), so that LLVM unrolls the
    small loops."""
    if nrow == 5 and fw == 5:
        _table_fits(sums, bits, k, j0, m, r0, 5, 5, n, rows, index, basis, p,
                    residual, want_low, cov, lin, line, skip, fits, fitted, partial, covs,
                    expl, dofk, levk, low)
    elif nrow == 7 and fw == 5:
        _table_fits(sums, bits, k, j0, m, r0, 7, 5, n, rows, index, basis, p,
                    residual, want_low, cov, lin, line, skip, fits, fitted, partial, covs,
                    expl, dofk, levk, low)
    else:
        _table_fits(sums, bits, k, j0, m, r0, nrow, fw, n, rows, index, basis, p,
                    residual, want_low, cov, lin, line, skip, fits, fitted, partial, covs,
                    expl, dofk, levk, low)


def linear_line(noise_line: tuple) -> np.ndarray:
    """(c0, slope, threshold) of a linear noise model (offset, slope, black, clamp, floor)
    for `_table_fits`: the model is c0 + slope * mu for every mu above the threshold and,
    where the threshold is finite, its constant c0 + slope * threshold below it (the
    clamp at the black level, the floor, the level held at 0); an infinite threshold: a
    line that is not increasing (each step's own variance)."""
    offset, slope, black, clamp, floor = (float(v) for v in noise_line)
    if slope == 0.0:  # a constant (at least the floor) at every level
        return np.array([max(offset, floor), 0.0, -np.inf])
    if not slope > 0.0:
        return np.array([0.0, 0.0, np.inf])  # never: each step's own variance
    threshold = max(0.0, black if clamp else 0.0, black + (floor - offset) / slope)
    return np.array([offset - slope * black, slope, threshold])


@njit(cache=True, error_model="numpy", nogil=True)
def fit_block(sums, bits, squares, j0, m, row0, nrows, steps, tables, skip, residual,
              want_low, cov, lin, line, leak, fits, fitted, covs, partial, rss, dof, lev, low,
              scratch, p):
    """phase.fit_set of every set over a block's pixels 0..m (input columns j0..):
    `fits[0..2, k]` alpha, beta, mean (float32), `fitted[k]`, `covs[0..2, k]` c_aa, c_bb,
    c_ab per unit variance and, where `partial[k]` (a least-squares fit on kept steps,
    `cov`: the noise is a line), `covs[3..5, k]` use_step_levels' numerators. With
    `residual`: the decoder's `_residuals` (rss, dof, dof-weighted level); with
    `want_low`, in `low` a step clipped at the dark end. `skip`: pixels seeing no screen
    (no fit where clipped)."""
    f32 = np.float32
    index, rows, basis, widths = tables
    expl, dofk, levk = scratch[0], scratch[1], scratch[2]
    sq = squares[j0:j0 + m]  # (empty where not kept)
    for j in range(m):
        rss[j] = float(sq[j]) if residual else 0.0
        dof[j] = 0.0
        lev[j] = 0.0
        low[j] = False
    for k in range(row0.shape[0]):
        r0, nrow, n = row0[k], nrows[k], steps[k]
        inv_n, scale = f32(1.0 / n), f32(2.0 / n)
        c = float(f32(2.0 / n))
        s0, sa, sb = sums[r0, j0:j0 + m], sums[r0 + 1, j0:j0 + m], sums[r0 + 2, j0:j0 + m]
        alpha, beta, mean, ok, part = fits[0, k], fits[1, k], fits[2, k], fitted[k], partial[k]
        caa, cbb, cab = covs[0, k], covs[1, k], covs[2, k]
        for j in range(m):  # every step kept: the closed form
            mean[j] = s0[j] * inv_n
            alpha[j] = sa[j] * scale
            beta[j] = sb[j] * scale
            ok[j] = True
            part[j] = False
            caa[j] = c
            cbb[j] = c
            cab[j] = 0.0
        if residual:
            explained(sums, r0, nrow, n, j0, m, expl)
            for j in range(m):
                dofk[j] = float(f32(n - nrow))
                levk[j] = mean[j]
        if bits.shape[0]:  # the pixels with clipped steps: least squares on the kept ones
            _table_fits_n(sums, bits, k, j0, m, r0, nrow, widths[k], n, rows, index, basis[k], p,
                          residual, want_low, cov, lin, line, skip, fits, fitted,
                          partial, covs, expl, dofk, levk, low)
        if residual:
            for j in range(m):
                rss[j] -= expl[j] if ok[j] else 0.0
                dof[j] += dofk[j] if ok[j] else 0.0
                lev[j] += float(f32(dofk[j]) * f32(levk[j])) if ok[j] else 0.0
            if leak[k] != 0.0:  # the display harmonic in an unclipped set's residual
                nyquist(sums, r0, n, j0, m, expl)
                for j in range(m):
                    clipped = bits.shape[0] > 0 and bits[k, j0 + j] != 0
                    rss[j] -= 0.0 if clipped else leak[k] * expl[j]


drop_stale_kernels(globals())  # before any kernel runs: no machine code from older sources
