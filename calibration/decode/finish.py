"""The compiled passes over a pixel range: the noise line's residual statistics and the
finish, straight from the range's sums in one numba pass each (kernel_sums.py). They
return the pixels the kernel leaves (clipped patterns without tables, noise models the
kernel cannot evaluate), which the decoder takes through its array path on a gathered copy
of their sums; what they read of the decoder it hands over as `FinishInputs`. The output
planes and the chi-square tail here serve both paths."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from calibration.decode.accumulate import FrameAccumulator
from calibration.decode.arrays import chi2_isf
from calibration.decode.axes import MIN_PERIOD_SNR, chi2_limits
from calibration.decode.batch import ChunkSums
from calibration.decode.noise import MIN_SPAN_DN, LinearVariance, NoiseModel, NoiseSource
from calibration.decode.options import DecodeOptions
from calibration.shared.plan import Plan

if TYPE_CHECKING:  # (a numba module: loaded only with the compiled path)
    from calibration.decode.kernel_clipped import PatternTables


@dataclass(frozen=True)
class FinishInputs:
    """What the compiled passes read of their decoder (`StreamingDecoder`), handed over once
    per pass over the image: the sums, the plan and options, and the noise as known then
    (before the photon-transfer line is fitted: each pixel's own residuals, no leak)."""

    acc: FrameAccumulator
    plan: Plan
    options: DecodeOptions
    floor: float  # smallest credible sample variance (quantization of integer frames)
    noise: np.ndarray | None  # the kernel's noise parameters (`noise_params`), None: a
    # given noise the kernel cannot evaluate (the decoder's array path decodes every pixel)
    leak: np.ndarray  # per set r^2 of the display harmonic in the residuals (zeros: none)
    tables: PatternTables | None  # clipped patterns' least squares (None: > 16 steps)


def output_planes(npix: int, axes: list[str], into: dict[str, np.ndarray] | None = None
                  ) -> dict[str, np.ndarray]:
    """(2, npix) output arrays (rows x, y): `into`'s (e.g. views of the maps file, whose rows
    are two members apart) or new ones, strided alike (each row padded) so the compiled
    kernel has one specialization for both; rows of axes the plan lacks are NaN."""
    planes = {}
    for name, dtype in (("position", np.float64), ("sigma", np.float32),
                        ("modulation", np.float32), ("blur", np.float32)):
        pad = 64 // np.dtype(dtype).itemsize
        arr = into[name] if into is not None else np.empty((2, npix + pad), dtype)[:, :npix]
        for row, axis in enumerate(("x", "y")):
            if axis not in axes:
                arr[row] = np.nan
        planes[name] = arr
    return planes


@functools.lru_cache(maxsize=8)
def chi2_tail(max_dof: int) -> np.ndarray:
    """Per-dof ratio chi2.isf(1e-6, d)/d for d = 0..max_dof (inf for d = 0)."""
    d = np.arange(max_dof + 1, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = chi2_isf(1e-6, np.maximum(d, 1)) / np.maximum(d, 1)
    ratio[0] = np.inf
    return ratio


def linear_noise(noise: Any) -> tuple[float, float, float, float] | None:
    """A given noise as (offset, slope, black, clamp) of `offset + slope * (level - black)`
    (clamped at 0 when `clamp`), or None when the kernel cannot evaluate it."""
    if isinstance(noise, bool):
        return None
    if isinstance(noise, int | float | np.floating | np.integer):
        return float(noise) ** 2, 0.0, 0.0, 0.0
    if isinstance(noise, NoiseModel):
        slope = 0.0 if noise.gain_e_per_dn is None else 1.0 / noise.gain_e_per_dn
        return noise.read_dn**2 + noise.quant_dn**2 / 12.0, slope, noise.black_dn, 1.0
    return None


def noise_params(noise: NoiseModel | NoiseSource | float | None, ptc: LinearVariance | None,
                 floor: float) -> np.ndarray | None:
    """The kernel's noise parameters: a given `noise` (None where the kernel cannot evaluate
    it: the array path for all), else the fitted photon-transfer line `ptc`, else each
    pixel's own residual variance; all held at or above `floor`."""
    from calibration.decode.kernel_sets import MODE_GIVEN, MODE_LINE, MODE_OWN

    if noise is not None:
        line = linear_noise(noise)
        return None if line is None else np.array([MODE_GIVEN, *line, floor, -np.inf])
    if ptc is None:
        return np.array([MODE_OWN, 0.0, 0.0, 0.0, 0.0, floor, -np.inf])
    return np.array([MODE_LINE, ptc.offset, ptc.slope, 0.0, 0.0, floor, ptc.floor])


def _inputs(chunk: ChunkSums, acc: FrameAccumulator) -> tuple[Any, ...]:
    """(sums, bits, squares, bright, dark, first column) as the kernels take them: C
    arrays (an empty bits block where no step clipped, empty squares where not kept)."""
    block, bits, squares, bright, dark = chunk.full or (
        chunk.block, chunk.bits, chunk.squares, chunk.bright, chunk.dark)
    if bits is None:
        bits = np.zeros((0, block.shape[1]), dtype=acc.bits_dtype)
    if squares is None:
        squares = np.empty(0, dtype=acc.squares_dtype)
    return block, bits, squares, bright, dark, chunk.col0 if chunk.full else 0


def _tables(inputs: FinishInputs, bits: np.ndarray, c0: int, n: int) -> tuple[np.ndarray, ...]:
    """The kernels' pattern tables covering columns c0..c0+n of `bits` (`kernel_tables`);
    empty arrays when the plan has more steps than the tables take, or when no step of the
    range clipped (the kernels then fit nothing: same results, without the scalar scan of
    the range's patterns, ~3 % of a finish's kernel time)."""
    from calibration.decode.kernel_clipped import no_tables  # (a numba module, as above)

    tables = inputs.tables
    if tables is None or not bits[:, c0:c0 + n].any():
        return no_tables()
    return tables.kernel_tables(bits, c0, n)


def residual_stats(inputs: FinishInputs, chunk: ChunkSums, lazy: bool = False
                   ) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
    """(level, rss, dof, clean, no_dark_clip, power) of a range for the noise line, and the
    pixels (indices in the range) left to the array path: those with clipped steps when
    the plan has no pattern tables. `lazy`: pixels with clipped steps and a flat contrast
    clear of `undithered`'s low group are not fitted (dof -1) until `line_pixels` needs
    them."""
    from calibration.decode.kernel_sums import residual_stats as kernel

    acc, n = inputs.acc, chunk.size
    lay = acc.kernel_layout
    level, rss, dof = (np.empty(n, dtype=np.float32) for _ in range(3))
    dirty, low = np.empty(n, dtype=np.bool_), np.zeros(n, dtype=np.bool_)
    power = np.empty((len(acc.sets), n), dtype=np.float32)
    block, bits, squares, bright, dark, c0 = _inputs(chunk, acc)
    tables = _tables(inputs, bits, c0, n)
    clip = np.array([inputs.floor, acc.n_bright, acc.n_dark, inputs.options.min_contrast_snr,
                     MIN_SPAN_DN + 0.5 if lazy else np.inf])  # (a margin over float32 spans)
    kernel(block, bits, squares, c0, lay.row0, lay.nrows, lay.steps, level, rss, dof, dirty,
           power, low, bright, dark, clip, inputs.leak, tables)
    left = np.flatnonzero(dirty) if tables[0].shape[0] == 0 else np.zeros(0, dtype=np.int64)
    return (level, rss, dof, ~dirty, ~low, power), left


def finish_range(inputs: FinishInputs, chunk: ChunkSums, sl: slice,
                 planes: dict[str, np.ndarray], reason: np.ndarray) -> np.ndarray:
    """Decode the pixel range `sl` (sums `chunk`) into `planes` and `reason`; returns the
    pixels (indices in the range) left to the array path, every one when the kernel
    cannot evaluate the noise."""
    from calibration.decode.kernel_clipped import linear_line
    from calibration.decode.kernel_sums import DIRTY, finish_sums

    acc, opt, plan, params = inputs.acc, inputs.options, inputs.plan, inputs.noise
    if params is None:
        return np.arange(chunk.size)
    sub_out = reason[sl]
    lay = acc.kernel_layout
    axis_of = np.array([0 if s.layout.axis == "x" else 1 for s in acc.sets], dtype=np.int64)
    per_axis = max(int((axis_of == a).sum()) for a in (0, 1))
    limits = chi2_limits(max(per_axis - 1, 0), opt.consistency_p)
    limits = np.concatenate([limits, np.full(len(acc.sets) + 1 - limits.size, np.inf)])
    kparams = np.array([opt.min_contrast_snr, opt.min_modulation_snr, opt.max_ambiguity,
                        opt.screen_margin_sigma, opt.edge_margin_blur, opt.max_sigma_px,
                        MIN_PERIOD_SNR])
    extents = np.array([plan.screen.extent_px(a) for a in ("x", "y")], dtype=np.float64)
    # the most residual dof a pixel can have: a partial fit may model fewer harmonics
    # than its set's rows (`phase.PARTIAL_MAX_ORDER`), the fundamental at least
    max_dof = int((lay.steps - 3).sum())
    kernel_inputs = _inputs(chunk, acc)
    tables = _tables(inputs, kernel_inputs[1], kernel_inputs[5], chunk.size)
    lin = linear_line(params[[1, 2, 3, 4, 6]])  # (offset, slope, black, clamp, floor)
    finish_sums(*kernel_inputs, lay.row0, lay.nrows, lay.steps, params, lin, inputs.leak,
                np.array([acc.n_bright, acc.n_dark], dtype=np.float64), chi2_tail(max_dof),
                axis_of, np.array([s.layout.period_px for s in acc.sets]),
                np.array([s.layout.amplitude for s in acc.sets]), limits, extents, kparams,
                planes["position"], planes["sigma"], planes["modulation"],
                planes["blur"], sl.start, sub_out, tables)
    return np.flatnonzero(sub_out == DIRTY)
