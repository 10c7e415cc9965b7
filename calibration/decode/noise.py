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
    """Noise variance linear in the mean level, `offset + slope * mean` (a photon-transfer line)."""

    offset: float
    slope: float

    def variance(self, mean_dn: Any) -> Any:
        """Noise variance (DN^2) at mean level `mean_dn`."""
        return self.offset + self.slope * mean_dn


def fit_photon_transfer(
    mean: np.ndarray,
    rss: np.ndarray,
    dof: np.ndarray,
    floor: float,
    bins: int = 16,
    max_pixels: int = 1 << 19,
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
    xs, ys, ws = [], [], []
    for b in range(len(edges) - 1):  # a loop over 16 bins, not over pixels
        sel = which == b
        count = int(sel.sum())
        if count < 16:
            continue
        level = float(np.median(ratio[sel]))
        if not level > 0:  # mostly constant readings (a black level under the noise): they
            continue  # say nothing about the line, and 1/y weights would be infinite
        xs.append(float(np.median(m[sel])))
        ys.append(level)
        ws.append(count)
    if len(xs) < 4:
        return None
    x, y, w = np.array(xs), np.array(ys), np.array(ws, dtype=np.float64)
    wt = w / y**2  # the polyfit weights squared: relative errors of the bin medians
    slope, offset = np.polyfit(x, y, 1, w=np.sqrt(wt))
    if slope < 0:
        slope, offset = 0.0, float(np.average(y, weights=w))
    elif offset < floor:
        # Constrained least squares: the offset at its floor, the slope refitted. (Clamping the
        # offset alone would lift the whole line where the levels span a narrow range.)
        offset = floor
        slope = max(float(np.sum(wt * x * (y - floor)) / np.sum(wt * x * x)), 0.0)
    return LinearVariance(offset=max(float(offset), floor), slope=float(slope))
