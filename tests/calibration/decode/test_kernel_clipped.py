"""The compiled least-squares fit of a pixel with clipped steps (kernel_clipped.py) against
phase.py's tables and `SetFit.use_step_levels`' per-step noise covariance, in NumPy."""

import numpy as np
import pytest

from acquisition.patterns import build_plan
from calibration.decode.accumulate import FrameAccumulator
from calibration.decode.kernel_clipped import _table_fits, linear_line, pattern_tables
from calibration.decode.phase import design_matrix, normal_inverse

# offset, slope, black, clamp, floor: a sensor line with a black level (clamped below it)
LINE = (0.8, 0.05, 6.0, True, 1.0 / 12.0)
# a photon-transfer line (no black level, not clamped) that reaches its floor at 6.0
FLOORED = (-0.22, 0.05, 0.0, False, 0.08)
PATTERNS = (0b0000000111, 0b1100000001, 0b0000110000)  # clipped steps (bit i: step i)


def _table_fit(col, r0, nrow, n, jc, rows, t, basis, p, residual, want_low, q, cov, lin, line,
               fw=5):
    """The kernel's fit of one pixel (column jc of `col`) whose set has clipped pattern q and
    table row t (`fw` columns fitted): (ok, mean, level, alpha, beta, c_aa, c_bb, c_ab,
    explained, dof, the use_step_levels numerators aa, bb, ab, a step clipped at the dark
    end)."""
    bits = np.zeros((1, col.shape[1]), dtype=np.uint16)
    bits[0, jc] = q
    index = np.full((1, 1 << n), -1, dtype=np.int64)
    index[0, q] = t
    fits = np.zeros((3, 1, 1), np.float32)
    fitted, partial = np.zeros((1, 1), bool), np.zeros((1, 1), bool)
    covs, expl, dofk, levk = np.zeros((6, 1, 1)), np.zeros(1), np.zeros(1), np.zeros(1)
    low = np.zeros(1, bool)
    _table_fits(col, bits, 0, jc, 1, r0, nrow, fw, n, rows, index, basis, p, residual,
                want_low, cov, np.asarray(lin, dtype=np.float64), line, np.zeros(1, bool), fits,
                fitted, partial, covs, expl, dofk, levk, low)
    return (bool(fitted[0, 0]), fits[2, 0, 0], levk[0], fits[0, 0, 0], fits[1, 0, 0],
            *covs[:3, 0, 0], expl[0], dofk[0], *covs[3:, 0, 0], bool(low[0]))


def expected(n: int, harmonics: tuple[int, ...], q: int, v: np.ndarray, line=LINE) -> tuple:
    """(coefficients, use_step_levels numerators aa, bb, ab) from phase.py's tables, with
    each step's variance from the noise `line`."""
    pat = normal_inverse(n, q, harmonics)
    basis = design_matrix(n, harmonics)
    kept = np.array([(q >> i) & 1 == 0 for i in range(n)])
    sums = (basis[kept].T @ v[kept]).astype(np.float32).astype(np.float64)
    p = pat.minv @ sums
    offset, slope, black, clamp, floor = line
    above = np.maximum(basis @ p, 0.0) - black
    var = np.maximum(offset + slope * (np.maximum(above, 0.0) if clamp else above), floor)
    ga, gb = pat.gains
    return sums, p, np.array([var @ (ga * ga), var @ (gb * gb), var @ (ga * gb)])


def _first_set_tables(noise):
    """A 10-step plan's accumulator, its pattern tables and their (index, rows) once
    PATTERNS were met in the first set."""
    plan = build_plan(1920, 1080, 0.2745, steps=10)
    acc = FrameAccumulator(plan, (4, 4), saturation_dn=None, need_squares=noise is None)
    tables = pattern_tables(acc.sets)
    bits = np.zeros((len(acc.sets), len(PATTERNS)), dtype=acc.bits_dtype)
    bits[0] = PATTERNS
    return (acc, tables, *tables.tables(bits, 0, bits.shape[1]))


@pytest.mark.parametrize("line", [LINE, FLOORED], ids=["black-level", "floor"])
@pytest.mark.parametrize("noise", [None, 1.5])  # residual mode (7 rows) / given (5 rows)
def test_table_fit_matches_phase_tables_and_step_levels(noise, line):
    """Coefficients and `use_step_levels`' numerators of the kernel's fit equal NumPy's on
    phase.py's tables, both where the noise line is linear over the fitted steps (the
    kernel's shortcut through the pattern's summed tables) and where some fitted steps lie
    below the black level or the line's floor (the summed tables corrected at those steps,
    and each step's own variance); the uncorrected shortcut there is wrong."""
    acc, tables, index, rows = _first_set_tables(noise)
    k, s = 0, acc.sets[0]
    n, nrow, fw = s.layout.steps, s.rows, int(tables.widths[k])
    lin = linear_line(np.array([*line[:3], float(line[3]), line[4]]))
    never = np.array([lin[0], lin[1], np.inf])  # the shortcut never taken
    always = np.array([lin[0], lin[1], -np.inf])  # the shortcut always taken
    rng = np.random.default_rng(7)
    psi = np.asarray(s.layout.psi)
    p_scratch = np.empty(tables.basis.shape[2])
    for q in PATTERNS:
        for level, amp, linear in ((200.0, 80.0, True), (7.0, 5.0, False)):
            v = level + amp * np.cos(psi + 0.3) + rng.normal(0.0, 1.0, n)
            sums, p, num = expected(n, s.harmonics, q, v, line)
            col = sums.astype(np.float32)[:, None]
            fits = {name: _table_fit(col, 0, nrow, n, 0, rows, index[k, q], tables.basis[k],
                                     p_scratch, noise is None, True, q, True, thr, line, fw)
                    for name, thr in (("auto", lin), ("never", never), ("always", always))}
            got = fits["auto"]
            assert got[0]
            np.testing.assert_allclose([got[1], got[3], got[4]], p[:3], rtol=1e-6)
            np.testing.assert_allclose(got[10:13], num, rtol=1e-9)
            np.testing.assert_allclose(fits["never"][10:13], num, rtol=1e-9)
            shortcut = np.allclose(fits["always"][10:13], num, rtol=1e-9)
            assert shortcut == linear  # (the shortcut is wrong below the black level)


def test_partial_fits_read_only_the_columns_they_model():
    """Fits on partial steps model harmonics up to phase.PARTIAL_MAX_ORDER: in residual mode
    (harmonic 3 modelled, 7 rows) `widths` is 5, every pattern's inverse is zero past it,
    the kernels' tables carry it, and the kernel's fit over those columns equals its fit
    over every row of the set to the bit (residuals, dark-end test, step variances)."""
    acc, tables, index, rows = _first_set_tables(None)
    k, s = 0, acc.sets[0]
    n, nrow, f = s.layout.steps, s.rows, tables.width
    assert (nrow, int(tables.widths[k])) == (7, 5)
    bits = np.zeros((len(acc.sets), 1), dtype=acc.bits_dtype)
    bits[0, 0] = PATTERNS[0]
    kernel_tables = tables.kernel_tables(bits, 0, 1)
    assert len(kernel_tables) == 4 and kernel_tables[3] is tables.widths
    lin = linear_line(np.array([*LINE[:3], 1.0, LINE[4]]))
    psi = np.asarray(s.layout.psi)
    p_scratch = np.empty(tables.basis.shape[2])
    for q in PATTERNS:
        minv = rows[index[k, q], :f * f].reshape(f, f)
        assert not minv[5:].any() and not minv[:, 5:].any() and minv[4, 4] != 0.0
        v = 7.0 + 5.0 * np.cos(psi + 0.3) + 0.4 * np.cos(3 * psi)  # steps below black
        col = expected(n, s.harmonics, q, v)[0].astype(np.float32)[:, None]
        narrow, wide = (_table_fit(col, 0, nrow, n, 0, rows, index[k, q], tables.basis[k],
                                   p_scratch, True, True, q, True, lin, LINE, fw)
                        for fw in (5, nrow))
        assert narrow == wide


@pytest.mark.parametrize("cov", [True, False])
def test_table_fit_skips_harmonic_rows_only_where_unused(cov):
    """With a given constant noise (no residuals, no dark-end test) the kernel computes only
    alpha, beta and the mean: they and the numerators equal the full fit's; the harmonic
    coefficients are then unused. A sum that is not finite still fails the fit."""
    acc, tables, index, rows = _first_set_tables(1.5)
    k, s = 0, acc.sets[0]
    n, nrow = s.layout.steps, s.rows
    constant = (2.25, 0.0, 0.0, False, 1.0 / 12.0)
    lin = linear_line(np.array([2.25, 0.0, 0.0, 0.0, 1.0 / 12.0]))
    assert lin[1] == 0.0 and lin[2] == -np.inf
    psi = np.asarray(s.layout.psi)
    p_scratch = np.empty(tables.basis.shape[2])
    for q in PATTERNS:
        v = 150.0 + 60.0 * np.cos(psi + 0.7) + 25.0 * np.cos(2 * psi + 0.2)  # a harmonic
        sums, p, _ = expected(n, s.harmonics, q, v)
        col = sums.astype(np.float32)[:, None]
        t, basis = index[k, q], tables.basis[k]
        fast = _table_fit(col, 0, nrow, n, 0, rows, t, basis, p_scratch, False, False, q, cov,
                          lin, constant)
        assert np.all(p_scratch[3:nrow] == 0.0)  # (not computed)
        full = _table_fit(col, 0, nrow, n, 0, rows, t, basis, p_scratch, False, True, q, cov,
                          lin, constant)  # the dark-end test needs every coefficient
        np.testing.assert_allclose(p_scratch[:nrow], p, rtol=1e-6)
        assert abs(p[3]) > 1.0  # the harmonic is there: zeroing it would show
        assert fast[:13] == full[:13]
        np.testing.assert_allclose([fast[1], fast[3], fast[4]], p[:3], rtol=1e-6)
        if cov:  # a finite threshold: each step's own variance from every coefficient
            never = np.array([lin[0], 0.0, np.inf])
            exact = [_table_fit(col, 0, nrow, n, 0, rows, t, basis, p_scratch, False, low, q,
                                True, never, LINE)[10:13] for low in (False, True)]
            assert exact[0] == exact[1]
        bad = col.copy()
        bad[nrow - 1] = np.inf  # only a harmonic row's sum: still no fit
        assert not _table_fit(bad, 0, nrow, n, 0, rows, t, basis, p_scratch, False, False, q,
                              cov, lin, constant)[0]


def test_pattern_tables_cover_every_partial_pattern_and_agree_across_decoders():
    """`tables` gives a row to every partial pattern of the columns asked (none to 0 or
    every step), the rows of the same pattern are the same in two decoders' tables (rows
    kept for the process), and a second call finds nothing new to build."""
    from calibration.decode.kernel_clipped import unknown_patterns

    plan = build_plan(1920, 1080, 0.2745, steps=10)
    first, second = (pattern_tables(FrameAccumulator(plan, (4, 4), saturation_dn=None,
                                                     need_squares=True).sets)
                     for _ in range(2))
    sets = len(first.sets)
    rng = np.random.default_rng(11)
    bits = rng.choice(np.array([0, 1023, *PATTERNS, 0b0110000000], dtype=np.uint16),
                      size=(sets, 300))
    index, rows = first.tables(bits, 0, 300)
    for k in range(sets):
        for q in np.unique(bits[k]).tolist():
            assert (index[k, q] >= 0) == (q not in (0, 1023)), (k, q)
    assert unknown_patterns(bits, 0, 300, index, first.set_steps).shape == (0, 2)
    assert first.tables(bits, 0, 300)[1] is rows  # nothing new: the same pair
    index2, rows2 = second.tables(bits[:, ::-1].copy(), 0, 300)  # other order of meeting
    for k in range(sets):
        for q in np.unique(bits[k]).tolist():
            if q not in (0, 1023):
                np.testing.assert_array_equal(rows2[index2[k, q]], rows[index[k, q]])
    fresh = np.zeros_like(rows[0])  # the row as PatternTables computed it before the cache
    k, q = 0, PATTERNS[0]
    pat = normal_inverse(10, q, first.sets[k].harmonics)
    f, w = first.width, pat.minv.shape[0]
    minv = np.zeros((f, f))
    minv[:w, :w] = pat.minv
    fresh[:f * f] = minv.ravel()
    fresh[f * f:f * f + w] = pat.weights
    assert np.array_equal(rows[index[k, q]][:f * f + f], fresh[:f * f + f])
    assert rows[index[k, q]][-2:].tolist() == [pat.kept, pat.used]
