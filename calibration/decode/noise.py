"""Per-sample camera noise: a sensor model (variance versus mean level), a constant, or a fit."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
from scipy.special import gammaincinv


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


@dataclass(frozen=True)
class LinearVariance:
    """Noise variance linear in the mean level, `offset + slope * mean` (a photon-transfer
    line), never below `floor` (quantization). `offset` is the line at 0 DN: below zero
    for a sensor whose black level exceeds `read^2 * gain` (variance = read^2 + q^2/12 +
    (mean - black) / gain), so the floor bounds the line, not its intercept."""

    offset: float
    slope: float
    floor: float = 0.0

    def variance(self, mean_dn: Any) -> Any:
        """Noise variance (DN^2) at mean level `mean_dn`."""
        return np.maximum(self.offset + self.slope * mean_dn, self.floor)


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
    8-bit fisheye). Low-contrast `candidates` whose pooled variance `sum rss / sum dof`
    shows dithering noise are honest points at the dark level and stay.
    """
    low = span < MIN_SPAN_DN
    group = low & candidates & (dof >= 1)
    if not quantized or not group.any():
        return np.zeros(span.shape, dtype=bool)
    pooled = float(np.sum(rss[group], dtype=np.float64) / np.sum(dof[group], dtype=np.float64))
    return low if pooled < DITHERED_VARIANCE else np.zeros(span.shape, dtype=bool)


def line_pixels(clean: np.ndarray, no_dark_clip: np.ndarray, spread: np.ndarray,
                dof: np.ndarray, minimum: int) -> np.ndarray:
    """The pixels the photon-transfer line is fitted on: the first choice with `minimum`.

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
    return use


def fit_photon_transfer(
    mean: np.ndarray,
    rss: np.ndarray,
    dof: np.ndarray,
    floor: float,
    bins: int = 16,
    max_pixels: int = 1 << 19,
    low: float | None = None,
) -> LinearVariance | None:
    """Fit the sensor's variance-versus-mean line to per-pixel cosine-fit residuals.

    Pixels are grouped into mean-level quantile bins; each bin's variance is the median of
    `rss/dof` over each pixel's chi-square median `chi2.median(dof)/dof` (pixels with
    clipped steps have fewer dof), which ignores the few pixels with model errors. A straight
    line through the bins (slope >= 0) gives every pixel a variance estimated from millions
    of residual degrees of freedom instead of its own handful; an even subsample of at most
    ~2 `max_pixels` pixels (~30000 per bin) is plenty. None when < 4 bins have data.
    """
    # Pixels reading one constant value (rss 0: e.g. a black level under the noise, off
    # the screen) say nothing about the line and would collapse the level quantiles.
    good = np.flatnonzero(np.isfinite(mean) & np.isfinite(rss) & (dof >= 1) & (rss > 0))
    if good.size < 64:
        return None
    good = good[:: max(1, good.size // max_pixels)]  # an even subsample bounds the work
    m, d = mean[good], np.rint(dof[good]).astype(np.int64)
    # Each ratio over its own dof's chi-square median (dof differ between pixels: clipped
    # steps leave fewer), so every bin's median estimates the variance itself.
    dofs = np.arange(1, int(d.max()) + 1)
    median = 2.0 * gammaincinv(dofs / 2.0, 0.5)  # chi-square medians
    ratio = rss[good] / d / (median / dofs)[d - 1]
    edges = np.unique(np.quantile(m, np.linspace(0.0, 1.0, bins + 1)))
    which = np.clip(np.searchsorted(edges, m, side="right") - 1, 0, len(edges) - 2)
    count = np.bincount(which, minlength=len(edges) - 1)
    keep = [b for b in range(len(edges) - 1) if count[b] >= 16]  # a loop over 16 bins
    x = np.array([float(np.median(m[which == b])) for b in keep])
    line: LinearVariance | None = None
    for _ in range(2):
        # Second pass: each ratio over the first line at its own level, so a bin whose levels
        # (hence variances) span a factor of several still gives the line at its median level
        # (the plain median of such a mixture sat 6 % low in the darkest bin).
        scale = np.ones(m.shape) if line is None else line.variance(m)
        at = np.ones(x.shape) if line is None else line.variance(x)
        y = np.array([float(np.median(ratio[which == b] / scale[which == b])) for b in keep]) * at
        ok = y > 0  # mostly constant readings (a black level under the noise) say nothing
        if ok.sum() < 4:  # about the line, and 1/y weights would be infinite
            return line
        line = _weighted_line(x[ok], y[ok], count[keep][ok].astype(np.float64), floor, low)
    return line


def _weighted_line(x: np.ndarray, y: np.ndarray, w: np.ndarray, floor: float,
                   low: float | None) -> LinearVariance:
    """Line through bin variances `y` at levels `x` (`w` pixels each, relative errors), slope
    >= 0 and at or above `floor` from level `low` (default: the lowest bin) up."""
    wt = w / y**2  # the polyfit weights squared: relative errors of the bin medians
    slope, offset = np.polyfit(x, y, 1, w=np.sqrt(wt))
    low = float(x.min()) if low is None else min(float(low), float(x.min()))
    if slope < 0:
        slope, offset = 0.0, max(float(np.average(y, weights=w)), floor)
    elif offset + slope * low < floor:
        # Constrained least squares: the line at its floor at the lowest level seen, the slope
        # refitted. (Clamping the offset alone would lift the whole line where the levels span
        # a narrow range; pinning it at 0 DN instead of the lowest level would bend it where
        # a black level makes the true intercept negative.)
        dx = x - low
        slope = max(float(np.sum(wt * dx * (y - floor)) / max(np.sum(wt * dx * dx), 1e-300)), 0.0)
        offset = floor - slope * low
    return LinearVariance(offset=float(offset), slope=float(slope), floor=floor)
