"""Per-sample camera noise: a sensor model (variance versus mean level), a constant, or a fit."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from calibration.decode.ptc_fit import LinearVariance, binned_line, level_bins
from calibration.decode.ptc_select import compiled, variance_ratio


@runtime_checkable
class NoiseSource(Protocol):
    """Anything giving the per-frame noise sigma (DN) at a mean level (DN), e.g. a sensor."""

    def noise_sigma_dn(self, mean_dn: Any) -> Any: ...


@dataclass(frozen=True)
class NoiseModel:
    """EMVA-1288-style noise: variance = read^2 + mean_above_black / gain + quantization.

    `read_dn` is the dark noise in DN, `gain_e_per_dn` the conversion gain (electrons per DN;
    shot-noise variance in DN^2 is signal/gain), `black_dn` the black level, `quant_dn` the
    quantization step (variance quant^2/12).
    """

    read_dn: float
    gain_e_per_dn: float | None = None
    black_dn: float = 0.0
    quant_dn: float = 1.0

    def __post_init__(self) -> None:
        if not self.read_dn >= 0:
            raise ValueError(f"NoiseModel.read_dn: must be >= 0, got {self.read_dn!r}")
        if self.gain_e_per_dn is not None and not self.gain_e_per_dn > 0:
            raise ValueError(f"NoiseModel.gain_e_per_dn: must be > 0, got {self.gain_e_per_dn!r}")
        if not self.quant_dn >= 0:
            raise ValueError(f"NoiseModel.quant_dn: must be >= 0, got {self.quant_dn!r}")

    def noise_sigma_dn(self, mean_dn: Any) -> Any:
        """Noise sigma (DN) of one sample whose expected value is `mean_dn`."""
        return self.variance(mean_dn) ** 0.5

    def variance(self, mean_dn: Any) -> Any:
        """Noise variance (DN^2) of one sample whose expected value is `mean_dn`."""
        var = self.read_dn**2 + self.quant_dn**2 / 12.0 + 0.0 * mean_dn
        if self.gain_e_per_dn is not None:
            signal = mean_dn - self.black_dn
            var = var + (signal * (signal > 0)) / self.gain_e_per_dn
        return var


VarianceFn = Callable[[Any], Any]


def variance_function(noise: NoiseModel | NoiseSource | float | None) -> VarianceFn | None:
    """The decoder's `noise` argument as mean -> variance, or None (estimate from residuals)."""
    if noise is None:
        return None
    if isinstance(noise, bool):
        raise TypeError("noise: expected a NoiseModel, an object with noise_sigma_dn() or sigma DN")
    if isinstance(noise, int | float | np.floating | np.integer):
        sigma = float(noise)
        if not (np.isfinite(sigma) and sigma > 0):
            raise ValueError(f"noise: sigma must be a finite number > 0 DN, got {noise!r}")
        return lambda mean: 0.0 * mean + sigma**2
    if isinstance(noise, NoiseModel):
        return noise.variance
    if isinstance(noise, NoiseSource):
        return lambda mean: noise.noise_sigma_dn(mean) ** 2
    raise TypeError(
        f"noise: expected a NoiseModel, an object with noise_sigma_dn(), or sigma DN, "
        f"got {type(noise).__name__}"
    )


# A pixel's samples span several codes when its flat contrast is at least this (DN).
MIN_SPAN_DN = 4.0
# Rounding is noise (variance q^2/12, signal-independent) under temporal noise of sigma >=
# ~0.45 q (Widrow: the ripple of the rounded variance is then < 2 %): variance (0.45^2 + 1/12) q^2.
DITHERED_VARIANCE = 0.45**2 + 1.0 / 12.0


def undithered(span: np.ndarray, rss: np.ndarray, dof: np.ndarray, candidates: np.ndarray,
               *, quantized: bool) -> np.ndarray:
    """Pixels whose rounding error is not noise, to keep out of the photon-transfer fit.

    Rounding to integer DN adds the variance q^2/12 of the line's model only when the value
    rounded is spread over the code grid: by a signal varying over several codes between the
    samples of a fit, or by temporal noise of sigma >= ~q/2. A pixel whose flat contrast
    `span` is under `MIN_SPAN_DN` (it sees no screen: a fisheye's dark surround, often most
    of its image) has only its temporal noise; under ~q/2 its readings mostly repeat one
    code and its residual variance is far below read^2 + q^2/12 (read 0.2 DN: ~0.03 DN^2,
    not 0.12). With many such pixels at the dark level the line's offset fell below the
    floor and the refit pulled its slope to ~0 (std of normalized errors 1.25-1.75 on an
    8-bit fisheye). Low-contrast `candidates` whose typical variance shows dithering noise
    are honest points at the dark level and stay.
    """
    low = span < MIN_SPAN_DN
    group = low & candidates & (dof >= 1)
    if not quantized or not group.any():
        return np.zeros(span.shape, dtype=bool)
    # the median: a few pixels at the screen's edge with model errors must not decide
    typical = float(np.median(variance_ratio(rss[group], np.rint(dof[group]).astype(np.int64))))
    return low if typical < DITHERED_VARIANCE else np.zeros(span.shape, dtype=bool)


def nyquist_power(xp: Any, fits: list, sets: list) -> list:
    """Per set, `nyquist_power_of` its fit."""
    return [nyquist_power_of(xp, f.alpha, f.beta, s.layout.steps, f.clipped)
            for f, s in zip(fits, sets, strict=True)]


def nyquist_power_of(xp: Any, alpha: Any, beta: Any, steps: int, clipped: Any) -> Any:
    """`N B^2 cos^2(N phi / 2)` of one set's fit: the residual sum of squares that a display
    harmonic of order N/2 with amplitude B (the fundamental's) adds (even N; odd N: 0).

    An even-N plan's last residual column is cos(N psi / 2) = (-1)^i: harmonic N/2 of the
    light, `h cos(N/2 (phi + psi_i))`, sums there to `N h cos(N phi / 2)` and adds
    `N h^2 cos^2(N phi / 2)` to the residual; h = r B with r the display's harmonic ratio.
    0 at `clipped` pixels (their kept steps have other residual columns).
    """
    if steps % 2:
        return xp.zeros(alpha.shape, dtype=xp.float32)
    b2 = alpha * alpha + beta * beta  # float32: a relative precision of 1e-7 is plenty here
    u = beta / xp.sqrt(xp.where(b2 > 0, b2, xp.float32(1.0)))  # cos(phi)
    prev, cheb = xp.ones_like(u), u  # Chebyshev T_k(cos phi) = cos(k phi)
    for _ in range(steps // 2 - 1):
        prev, cheb = cheb, xp.float32(2.0) * u * cheb - prev
    return xp.where(clipped, xp.float32(0.0), xp.float32(steps) * b2 * cheb * cheb)


def phase_level(xp: Any, fit: Any, sums: Any, sl: slice) -> Any:
    """Level (DN) whose noise variance is the phase's, for pixels with all steps kept.

    The phase rests on the steps where the fundamental crosses its mean (gain ~ sin theta_i,
    theta = phi + psi), not on its peaks. With noise linear in the level, the phase variance
    is `sum_i var(mu_i) sin^2 theta_i` over `sum_i sin^2 theta_i` times the usual factor,
    which puts the level at `C - h2c / 2`: h2c, the second harmonic in phase with the
    fundamental (display gamma without LUT: positive, the light at the crossings is below
    the mean), is the only fitted term that does not cancel. The mean level C overstated
    the phase noise there (normalized-error std 0.92 with the true sensor model too).
    """
    if 2 not in sums.harmonics:
        return xp.maximum(fit.mean, 0.0)
    j, scale = 2 * sums.harmonics.index(2), 2.0 / sums.layout.steps
    s2, c2 = (sums.extra[j + k].reshape(-1)[sl] * scale for k in (0, 1))
    b2 = fit.b2
    safe = xp.where(b2 > 0, b2, 1.0)
    h2c = (c2 * (fit.beta**2 - fit.alpha**2) + s2 * 2.0 * fit.alpha * fit.beta) / safe
    return xp.maximum(fit.mean - 0.5 * h2c, 0.0)


def harmonic_leak(rss: np.ndarray, dof: np.ndarray, level: np.ndarray, power: np.ndarray,
                  first: LinearVariance | None, max_rows: int = 1 << 16) -> np.ndarray | None:
    """Per set, the squared harmonic ratio r^2 of the display's harmonic N/2 in the residuals.

    Display gamma without a LUT puts harmonics into the light, phase-locked to the
    fundamental and in the same ratio at every pixel (the display's response; camera blur
    lowers it a little on the finest periods, hence one ratio per set). Harmonic N/2 falls
    into an even-N plan's last residual column: with 6 steps (`fast`) it is the residual's
    only degree of freedom per set, and taken for noise it overstated sigma (std 0.70 on a
    150-degree fisheye, gamma 2.2 without LUT). A weighted least-squares fit across pixels
    of `rss = dof (a + b level) + sum_s r_s^2 power_s` separates it (`power` from
    `nyquist_power`, (sets, pixels)); the caller subtracts `r^2 power` before fitting the
    noise line. Rows: relative weights from the `first` (contaminated) line; pixels with
    residuals over 10x it (model errors) left out. A ratio not 5 standard errors above 0 is
    taken as 0 (subtracting a fitted noise-level ratio would only take noise away). None
    without an even-N set, or when the harmonic is under 1 % of the residual variance
    (gamma 2.2's harmonic 4 in an 8-step plan: ~0.1 %).
    """
    step = max(1, rss.size // max_rows)
    # (power 0 at every row the fit sees: r^2 0, None)
    if first is None or rss.size < 1000 or not power[:, ::step].any():
        return None
    design, rhs, dv, kept_power, used = _leak_rows(rss, dof, level, power, step, first)
    used = np.flatnonzero(used)  # sets with even steps and pixels
    coef = np.zeros(design.shape[1])
    every = used.size == design.shape[1]  # (no copy: lstsq copies it anyway)
    coef[used] = np.linalg.lstsq(design if every else design[:, used], rhs, rcond=None)[0]
    scatter = np.sum((design @ coef - rhs) ** 2) / max(design.shape[0] - used.size, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.sqrt(scatter / np.einsum("ij,ij->j", design, design))  # uncorrelated approx
    r2 = np.where(coef[2:] > 5.0 * err[2:], coef[2:], 0.0)
    # Under 1 % of the residual variance (an 8-step plan's harmonic 4): not worth its cost.
    share = float(np.sum(r2 * kept_power.mean(axis=1)) / np.mean(dv))
    return r2 if share >= 0.01 else None


def _leak_rows(rss: np.ndarray, dof: np.ndarray, level: np.ndarray, power: np.ndarray,
               step: int, first: LinearVariance) -> tuple[np.ndarray, ...]:
    """`harmonic_leak`'s rows (every `step`-th pixel, those under 10x the `first` line): the
    weighted design, its right-hand side, `dof * var`, the harmonic powers, the columns
    used (nonzero, no NaN). One compiled pass where numba is loaded (float32 inputs, a
    positive floor: NumPy's maximum may order zeros of both signs otherwise)."""
    kernels = compiled()
    if kernels is not None and first.floor > 0 and \
            all(a.dtype == np.float32 for a in (rss, dof, level, power)):
        line = np.array([first.offset, first.slope, first.floor], dtype=np.float32)
        design, rhs, dv, kept, used, k = kernels.leak_rows(
            *(np.ascontiguousarray(a) for a in (rss, dof, level)), power, step, line)
        return design[:k], rhs[:k], dv[:k], kept[:, :k], used
    rss, dof, level, power = rss[::step], dof[::step], level[::step], power[:, ::step]
    var = np.asarray(first.variance(level), dtype=np.float64)
    ok = rss < 10.0 * dof * var
    w = 1.0 / (dof * var)[ok]
    design = np.column_stack([dof[ok] * w, dof[ok] * level[ok] * w, *(p[ok] * w for p in power)])
    return design, rss[ok] * w, dof[ok] * var[ok], power[:, ok], np.abs(design).sum(axis=0) > 0


def sample_pieces(npix: int, chunk: int, piece: int, total: int) -> list[slice]:
    """Pixel ranges the photon-transfer line is fitted on: all pixels (in `chunk`s), or
    evenly spread pieces of `piece` pixels, about `total` in all, on larger images."""
    if npix <= total:
        return [slice(s, min(s + chunk, npix)) for s in range(0, npix, chunk)]
    starts = np.linspace(0, npix - piece, total // piece)
    return [slice(int(s), int(s) + piece) for s in starts]


def residual_line(mean: np.ndarray, rss: np.ndarray, dof: np.ndarray, power: np.ndarray,
                  floor: float, dark: np.ndarray) -> tuple[LinearVariance | None, Any]:
    """The noise line of the residuals and the display harmonic's per-set r^2 (None if not
    found): a first line, the harmonic fitted against it (`harmonic_leak`), subtracted, and
    the line fitted again; at or above `floor` from the median `dark` flat level up.
    (Its least squares on one BLAS thread: NumPy's second one only spins.)"""
    from calibration.models.blas_threads import single_thread_blas

    with single_thread_blas(scipy=False):
        return _residual_line(mean, rss, dof, power, floor, dark)


def _residual_line(mean: np.ndarray, rss: np.ndarray, dof: np.ndarray, power: np.ndarray,
                   floor: float, dark: np.ndarray) -> tuple[LinearVariance | None, Any]:
    """`residual_line` with the BLAS threads set."""
    low = float(np.median(dark)) if dark.size else None
    binned = level_bins(mean, rss, dof)
    line = binned_line(binned, rss, dof, floor, low)
    leak = harmonic_leak(rss, dof, mean, power, line)
    if leak is None:
        return line, None
    rss = np.maximum(rss - leak.astype(np.float32) @ power, 0.0)
    binned = level_bins(mean, rss, dof, previous=binned)  # (the same levels: little to redo)
    return binned_line(binned, rss, dof, floor, low), [float(r2) for r2 in leak]


def line_sample(run: Callable[[bool], None], clean: np.ndarray, no_dark_clip: np.ndarray,
                span: np.ndarray, rss: np.ndarray, dof: np.ndarray, minimum: int,
                dtype: np.dtype) -> np.ndarray:
    """`line_pixels` of the noise sample, less `undithered`'s pixels: `run(lazy)` fills the
    arrays, first lazily (pixels with clipped steps outside the low-contrast group deferred,
    their fits the costliest), then again with every pixel fitted if the line needs them."""
    for lazy in (True, False):
        run(lazy)
        spread = ~undithered(span, rss, dof, no_dark_clip, quantized=dtype.kind == "u")
        use = line_pixels(clean, no_dark_clip, spread, dof, minimum)
        if use is not None:
            return use
    raise AssertionError("line_pixels deferred pixels after a full pass")


def line_pixels(clean: np.ndarray, no_dark_clip: np.ndarray, spread: np.ndarray,
                dof: np.ndarray, minimum: int) -> np.ndarray | None:
    """The pixels the photon-transfer line is fitted on: the first choice with `minimum`;
    None when it lacks them and some pixels' fits were deferred (dof < 0: fit them first).

    Pixels with clipped steps are left out when enough others exist: excluding the clipped
    samples truncates the noise of those near the clip level (censoring). When too few are
    left (heavy overexposure: every on-screen pixel clips), pixels clipped only at the bright
    end are used (their residual levels weigh each kept step, so they are unbiased to first
    order); those clipped at the dark end (0 DN, where a sensor without black offset
    truncates its read noise) are not. Pixels whose rounding is not noise (`spread` false,
    see `undithered`) are left out unless nothing else is left.
    """
    use = dof >= 1
    for choice in (clean & spread, no_dark_clip & spread, clean, no_dark_clip):
        if np.count_nonzero(use & choice) >= minimum:
            return use & choice
        if (dof < 0).any():
            return None
    return use
