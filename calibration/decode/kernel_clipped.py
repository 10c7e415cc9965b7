"""Compiled per-pixel fits of pixels with clipped steps (numba), for kernel_sums.py.

The same arithmetic as phase.py `fit_set` on the kept steps (the least-squares tables of
each exclusion pattern from `_normal_inverse`, gathered into `PatternTables`), the
decoder's residuals and noise variances (`_residuals`, `_noise_variances` with
`use_step_levels`) and the flat contrast, one pixel at a time (such pixels have few
patterns but no common closed form); then kernel.py's `decode_pixel`. Float32 rounding
where the array path keeps float32 arrays.
"""

from __future__ import annotations

import math
import threading

import numpy as np
from numba import njit

from calibration.decode.kernel import P_MIN_CONTRAST, decode_pixel
from calibration.decode.kernel_cache import drop_stale_kernels
from calibration.decode.phase import _basis, _normal_inverse
from calibration.decode.vecmath import atan2

MAX_TABLE_STEPS = 16  # dense pattern index per set: 2^steps entries (steps above: array path)
MODE_GIVEN, MODE_LINE, MODE_OWN = 0, 1, 2  # as kernel_sums (given / photon-transfer / own)
# Reassociation lets LLVM split the small dot products' sums over several registers (one
# chain of dependent additions per sum cost ~1.5 us per pixel); NaN and inf tests stay.
_FAST = {"reassoc", "contract", "nsz", "arcp"}


class PatternTables:
    """Least-squares tables of the exclusion patterns met so far, per set: `index[k, mask]`
    is the row of `rows` (-1: not built yet); each row holds minv (F x F), the residual
    weights (F), the gains (2 x T), kept and used steps. `basis[k]`: the (T, F) design."""

    def __init__(self, sets: list) -> None:
        self.sets = sets
        self.width = max(s.rows for s in sets)
        self.steps = max(s.layout.steps for s in sets)
        # (index, rows) replaced as one tuple: a thread never pairs a new index with old rows
        self._pair = (np.full((len(sets), 1 << self.steps), -1, dtype=np.int64),
                      np.zeros((0, self.row_size), dtype=np.float64))
        self.basis = np.zeros((len(sets), self.steps, self.width))
        for k, s in enumerate(sets):
            b = _basis(s.layout.steps, s.harmonics)
            self.basis[k, :b.shape[0], :b.shape[1]] = b
        self.set_steps = np.array([s.layout.steps for s in sets], dtype=np.int64)
        self._lock = threading.Lock()

    @property
    def row_size(self) -> int:
        """Values per table row."""
        return self.width * self.width + self.width + 2 * self.steps + 2

    def tables(self, bits: np.ndarray, c0: int, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(index, rows) covering every pattern of columns c0..c0+n of `bits` (built as
        needed; a consistent pair that later growth does not change)."""
        pair = self._pair
        if bits.shape[0] == 0 or not unknown_patterns(bits, c0, n, pair[0], self.set_steps):
            return pair
        with self._lock:
            index, rows = self._pair[0].copy(), [self._pair[1]]
            count = rows[0].shape[0]
            f, t = self.width, self.steps
            for k, s in enumerate(self.sets):
                every = (1 << s.layout.steps) - 1
                for mask in np.unique(bits[k, c0:c0 + n]).tolist():
                    if mask in (0, every) or index[k, mask] >= 0:
                        continue
                    pat = _normal_inverse(s.layout.steps, int(mask), s.harmonics)
                    row = np.zeros(self.row_size)
                    w, steps = pat.minv.shape[0], s.layout.steps
                    minv = np.zeros((f, f))
                    minv[:w, :w] = pat.minv
                    gains = np.zeros((2, t))
                    gains[:, :steps] = pat.gains
                    row[:f * f] = minv.ravel()
                    row[f * f:f * f + w] = pat.weights
                    row[f * f + f:f * f + f + 2 * t] = gains.ravel()
                    row[-2:] = pat.kept, pat.used
                    index[k, mask] = count
                    rows.append(row[None])
                    count += 1
            self._pair = (index, np.concatenate(rows))
            return self._pair


def pattern_tables(acc) -> PatternTables | None:
    """The accumulator's pattern tables (created once), None for plans of > 16 steps."""
    tables = getattr(acc, "_pattern_tables", None)
    if tables is None and max(s.layout.steps for s in acc.sets) <= MAX_TABLE_STEPS:
        tables = acc._pattern_tables = PatternTables(acc.sets)
    return tables


@njit(cache=True, error_model="numpy", nogil=True)
def unknown_patterns(bits, c0, n, index, steps) -> bool:
    """True when columns c0..c0+n of `bits` hold a partial pattern without a table row."""
    for k in range(bits.shape[0]):
        row, known, every = bits[k], index[k], (1 << steps[k]) - 1
        for j in range(c0, c0 + n):
            q = row[j]
            if q != 0 and q != every and known[q] < 0:
                return True
    return False


@njit(cache=True, error_model="numpy", inline="always", fastmath=_FAST)
def _nyquist(a, b, steps) -> float:
    """noise.nyquist_power_of one pixel (float32 arithmetic as there)."""
    f32 = np.float32
    if steps % 2:
        return 0.0
    b2 = a * a + b * b
    u = b / f32(math.sqrt(b2 if b2 > 0 else f32(1.0)))
    prev, cheb = f32(1.0), u
    for _ in range(steps // 2 - 1):
        prev, cheb = cheb, f32(2.0) * u * cheb - prev
    return float(f32(steps) * b2 * cheb * cheb)


@njit(cache=True, error_model="numpy", nogil=True, fastmath=_FAST)
def fit_pixel(sums, bits, j, row0, nrows, steps, index, rows, basis, skip, residual, fit, p):
    """phase.fit_set of every set at column j. `fit` (S, 9) float64 out: mean, level,
    alpha, beta, c_aa, c_bb, c_ab, explained, dof; then (S, 3) flags in `fit[:, 9:]`: ok,
    clipped, low_clipped. `p` (S, F) out: the coefficients of partial fits (else 0)."""
    f32 = np.float32
    width = basis.shape[2]
    t_max = basis.shape[1]
    for k in range(row0.shape[0]):
        r0, nrow, n = row0[k], nrows[k], steps[k]
        q = bits[k, j] if bits.shape[0] else 0
        every = (1 << n) - 1
        s0 = sums[r0, j]
        c = float(f32(2.0 / n))
        fit[k, 0] = fit[k, 1] = float(s0 * f32(1.0 / n))
        fit[k, 2] = float(sums[r0 + 1, j] * f32(2.0 / n))
        fit[k, 3] = float(sums[r0 + 2, j] * f32(2.0 / n))
        fit[k, 4] = fit[k, 5] = c
        fit[k, 6] = 0.0
        fit[k, 8] = float(f32(n - nrow))
        fit[k, 9], fit[k, 10], fit[k, 11] = 1.0, 0.0, 0.0
        for i in range(width):  # (element loops, not slices: a view costs a refcount)
            p[k, i] = 0.0
        if residual:
            e = float(s0) ** 2 / n
            for r in range(1, nrow):
                e += float(sums[r0 + r, j]) ** 2 * (2.0 / n)
            fit[k, 7] = e
        if q == 0:
            continue
        fit[k, 10] = 1.0
        if q == every or skip:  # no fit: every step clipped, or no screen seen
            for col in (0, 1, 2, 3, 7, 8, 9):
                fit[k, col] = 0.0
            continue
        t = index[k, q]
        good = True
        for i in range(width):
            acc = 0.0
            for m in range(nrow):
                acc += rows[t, i * width + m] * float(sums[r0 + m, j])
            p[k, i] = acc
            good = good and math.isfinite(acc)
        if not good:
            for i in range(width):
                p[k, i] = 0.0
        kept, used = rows[t, rows.shape[1] - 2], rows[t, rows.shape[1] - 1]
        lev = 0.0
        e = 0.0
        for i in range(nrow):
            lev += rows[t, width * width + i] * p[k, i]
            e += p[k, i] * float(sums[r0 + i, j])
        fit[k, 0] = float(f32(p[k, 0]))
        fit[k, 1] = float(f32(lev / max(kept - used, 1.0)))
        fit[k, 2] = float(f32(p[k, 1]))
        fit[k, 3] = float(f32(p[k, 2]))
        fit[k, 4] = float(f32(rows[t, width + 1])) if good else 0.0
        fit[k, 5] = float(f32(rows[t, 2 * width + 2])) if good else 0.0
        fit[k, 6] = float(f32(rows[t, width + 2])) if good else 0.0
        fit[k, 7] = e
        fit[k, 8] = float(f32(max(kept - used, 0.0)))
        fit[k, 9] = 1.0 if good else 0.0
        low = False
        for i in range(min(n, t_max)):
            if (q >> i) & 1:
                mu = 0.0
                for m in range(width):
                    mu += p[k, m] * basis[k, i, m]
                low = low or mu < p[k, 0]
        fit[k, 11] = 1.0 if low else 0.0


@njit(cache=True, error_model="numpy", inline="always", fastmath=_FAST)
def _residual(fit, sums, row0, steps, squares, j, leak):
    """decoder `_residuals` of one pixel: (rss, dof, level)."""
    f32 = np.float32
    rss = float(squares[j])
    dof = 0.0
    level = 0.0
    for k in range(row0.shape[0]):
        ok = fit[k, 9] != 0.0
        rss -= fit[k, 7] if ok else 0.0
        if leak[k] != 0.0 and fit[k, 10] == 0.0:
            rss -= float(f32(leak[k]) * f32(_nyquist(f32(fit[k, 2]), f32(fit[k, 3]), steps[k])))
        if ok:
            dof += fit[k, 8]
            level += fit[k, 8] * fit[k, 1]
    return max(rss, 0.0), dof, level / max(dof, 1.0)


@njit(cache=True, error_model="numpy", inline="always", fastmath=_FAST)
def _variance(line, level: float) -> float:
    """kernel_sums._line: offset + slope * (level - black)+, at least the floor."""
    offset, slope, black, clamp, floor = line
    x = level - black
    x = 0.0 if clamp and not x > 0.0 else x
    return max(offset + slope * x, floor)


@njit(cache=True, error_model="numpy", nogil=True, fastmath=_FAST)
def clipped_pixel(sums, bits, squares, bright, dark, j, row0, nrows, steps, index, rows, basis,
                  mode, line, floor, tail, leak, flats, set_axis, periods, amps, chi2_limit,
                  extents, params, pos_out, sig_out, mod_out, blur_out, o, fit, p, alpha, beta,
                  wrapped, var, c_aa, c_bb, c_ab, ok) -> int:
    """Decode the pixel at input column j (outputs at column o); its reason code. `fit`,
    `p`: fit_pixel's scratch; alpha..c_ab (S,) float32 and `ok` (S,) bool scratch."""
    f32 = np.float32
    nb, nd = flats[0], flats[1]
    lit, unlit = bright[j] / nb, dark[j] / nd
    floor_sigma = math.sqrt(floor * (1.0 / nb + 1.0 / nd))
    skip = not (lit - unlit) >= params[P_MIN_CONTRAST] * floor_sigma
    fit_pixel(sums, bits, j, row0, nrows, steps, index, rows, basis, skip, mode != MODE_GIVEN,
              fit, p)
    own = 0.0
    excess = False
    if mode != MODE_GIVEN:
        rss, dof, _ = _residual(fit, sums, row0, steps, squares, j, leak)
        own = max(rss / max(dof, 1.0), floor) if dof > 0 else np.nan
        if mode == MODE_LINE:
            excess = own > _variance(line, max(float(f32(fit[0, 0])), 0.0)) * tail[int(dof)]
    width = basis.shape[2]
    for k in range(row0.shape[0]):
        r0, n = row0[k], steps[k]
        a, b = f32(fit[k, 2]), f32(fit[k, 3])
        alpha[k], beta[k] = a, b
        mean = f32(fit[k, 0])
        level = max(mean, f32(0.0))
        if nrows[k] > 3:  # noise.phase_level: raw harmonic-2 sums, the fit's alpha, beta
            scale = f32(2.0 / n)
            s2, c2 = sums[r0 + 3, j] * scale, sums[r0 + 4, j] * scale
            b2 = a * a + b * b
            h2c = (c2 * (b * b - a * a) + s2 * f32(2.0) * a * b) / (b2 if b2 > 0 else f32(1.0))
            level = max(mean - f32(0.5) * h2c, f32(0.0))
        v = own if mode == MODE_OWN or excess else _variance(line, float(level))
        var[k] = v
        c_aa[k], c_bb[k], c_ab[k] = fit[k, 4], fit[k, 5], fit[k, 6]
        ok[k] = fit[k, 9] != 0.0
        partial = fit[k, 10] != 0.0 and ok[k] and mode != MODE_OWN and not excess
        if partial and var[k] > 0:  # SetFit.use_step_levels: each kept step's own variance
            t = index[k, bits[k, j]]
            g0 = width * width + width
            saa = sbb = sab = 0.0
            for i in range(n):
                mu = 0.0
                for m in range(width):
                    mu += p[k, m] * basis[k, i, m]
                vi = _variance(line, max(mu, 0.0))
                ga, gb = rows[t, g0 + i], rows[t, g0 + basis.shape[1] + i]
                saa += vi * ga * ga
                sbb += vi * gb * gb
                sab += vi * ga * gb
            base = float(var[k])
            c_aa[k], c_bb[k], c_ab[k] = saa / base, sbb / base, sab / base
        w = f32(atan2(-float(a), float(b))) * f32(periods[k] / (2.0 * math.pi))
        wrapped[k] = w + f32(periods[k]) if w < 0 else w
    if mode == MODE_OWN:
        var_b = var_d = own
    else:
        var_b, var_d = _variance(line, lit), _variance(line, max(unlit, 0.0))
    q = (lit - unlit) / math.sqrt(var_b / nb + var_d / nd)
    q = q if abs(q) < np.inf else 0.0
    return decode_pixel(alpha, beta, wrapped, var, c_aa, c_bb, c_ab, ok, q, set_axis, periods,
                        amps, chi2_limit, extents, params, pos_out, sig_out, mod_out, blur_out, o)


@njit(cache=True, error_model="numpy", nogil=True, fastmath=_FAST)
def clipped_residuals(sums, bits, squares, bright, dark, j, row0, nrows, steps, index, rows,
                      basis, floor, flats, min_contrast, leak, fit, p, power_out, o):
    """finish.residual_arrays of the pixel at column j: (level, rss, dof, clean,
    no_dark_clip); `power_out[:, o]` gets each set's Nyquist power (0 where clipped)."""
    nb, nd = flats[0], flats[1]
    lit, unlit = bright[j] / nb, dark[j] / nd
    skip = not (lit - unlit) >= min_contrast * math.sqrt(floor * (1.0 / nb + 1.0 / nd))
    fit_pixel(sums, bits, j, row0, nrows, steps, index, rows, basis, skip, True, fit, p)
    rss, dof, level = _residual(fit, sums, row0, steps, squares, j, leak)
    clean = True
    low = False
    for k in range(row0.shape[0]):
        clipped = fit[k, 10] != 0.0
        clean = clean and not clipped
        low = low or fit[k, 11] != 0.0
        f32 = np.float32
        power_out[k, o] = 0.0 if clipped else _nyquist(f32(fit[k, 2]), f32(fit[k, 3]), steps[k])
    return level, rss, dof, clean, not low


@njit(cache=True, error_model="numpy", nogil=True, fastmath=_FAST)
def clipped_block(m, dirty, dead, sums, bits, squares, bright, dark, j0, row0, nrows, steps,
                  tables, mode, line, floor, tail, leak, flats, set_axis, periods, amps,
                  chi2_limit, extents, params, pos_out, sig_out, mod_out, blur_out, o0,
                  reason) -> None:
    """`clipped_pixel` for the block's pixels 0..m (input columns j0.., outputs o0..) that
    are `dirty` but not `dead` (every step clipped); `tables`: (index, rows, basis)."""
    index, rows, basis = tables
    if index.shape[0] == 0:
        return  # no tables (a plan of > 16 steps): the array path takes them
    todo = False
    for j in range(m):
        todo = todo or (dirty[j] and not dead[j])
    if not todo:
        return
    n_sets = row0.shape[0]
    fit = np.empty((n_sets, 12))
    p = np.empty((n_sets, basis.shape[2]))
    f32 = np.float32
    alpha, beta, wrapped, var = (np.empty(n_sets, f32), np.empty(n_sets, f32),
                                 np.empty(n_sets, f32), np.empty(n_sets, f32))
    c_aa, c_bb, c_ab = np.empty(n_sets, f32), np.empty(n_sets, f32), np.empty(n_sets, f32)
    ok = np.empty(n_sets, dtype=np.bool_)
    for j in range(m):
        if dirty[j] and not dead[j]:
            reason[j] = clipped_pixel(
                sums, bits, squares, bright, dark, j0 + j, row0, nrows, steps, index, rows,
                basis, mode, line, floor, tail, leak, flats, set_axis, periods, amps,
                chi2_limit, extents, params, pos_out, sig_out, mod_out, blur_out, o0 + j, fit,
                p, alpha, beta, wrapped, var, c_aa, c_bb, c_ab, ok)


drop_stale_kernels(globals())  # before any kernel runs: no machine code from older sources
