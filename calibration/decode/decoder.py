"""`StreamingDecoder`: frames in (any order), `phasecal.maps/1` decoded maps out.

The per-frame work is only the accumulation (accumulate.py); `finish` fits each period
(phase.py), estimates the noise, unwraps (unwrap.py), fits blur (blur.py) and applies the
validity rules (validity.py), chunk by chunk over the pixels to bound temporary memory.
"""

from __future__ import annotations

import functools
import math
import os
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from types import ModuleType
from typing import Any

import numpy as np

from calibration.decode.accumulate import DecodeError, FrameAccumulator
from calibration.decode.arrays import array_module, chi2_isf, to_host
from calibration.decode.axes import decode_axes_compiled, decode_axes_xp
from calibration.decode.noise import (
    LinearVariance,
    NoiseModel,
    NoiseSource,
    VarianceFn,
    line_pixels,
    nyquist_power,
    phase_level,
    residual_line,
    sample_pieces,
    undithered,
    variance_function,
)
from calibration.decode.options import DecodeOptions
from calibration.decode.phase import SetFit, fit_set
from calibration.decode.validity import REASONS, mark_screen_edges
from calibration.maps import MAPS_FORMAT, DecodedMaps
from calibration.plan import Plan
from calibration.progress import CancelCheck, Cancelled, ProgressFn

# The photon-transfer fit uses only pixels without clipped steps when at least this many exist.
_MIN_CLEAN_PIXELS = 2000
# Larger images fit the photon-transfer line on evenly spread pieces of this many pixels,
# about _NOISE_SAMPLE in all (the fit needs ~1e5 pixels; the rest only costs time).
_NOISE_PIECE = 1 << 14
_NOISE_SAMPLE = 1 << 20
_COMPILED_MIN_PIXELS = 1 << 20


def _output_planes(npix: int, axes: list[str]) -> dict[str, np.ndarray]:
    """(2, npix) output arrays (rows x, y) for the compiled kernel; absent axes stay NaN."""
    planes = {}
    for name, dtype in (("position", np.float64), ("sigma", np.float32),
                        ("modulation", np.float32), ("blur", np.float32)):
        arr = np.empty((2, npix), dtype=dtype)
        for row, axis in enumerate(("x", "y")):
            if axis not in axes:
                arr[row] = np.nan
        planes[name] = arr
    return planes


@functools.lru_cache(maxsize=8)
def _chi2_tail(max_dof: int) -> np.ndarray:
    """Per-dof ratio chi2.isf(1e-6, d)/d for d = 0..max_dof (inf for d = 0)."""
    d = np.arange(max_dof + 1, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = chi2_isf(1e-6, np.maximum(d, 1)) / np.maximum(d, 1)
    ratio[0] = np.inf
    return ratio


def _software_version() -> str:
    """Installed phasecal version, or 'unknown' when running from a bare checkout."""
    try:
        from importlib.metadata import version

        return version("phasecal")
    except Exception:
        return "unknown"


class StreamingDecoder:
    """Accepts one pose's frames one at a time (`add`), then decodes them (`finish`).

    Implements `acquisition.sinks.FrameSink`. `noise` is the per-frame camera noise: a
    `NoiseModel`, any object with `noise_sigma_dn(mean)` (e.g. a sensor model), a constant
    sigma in DN, or None to estimate it per pixel from the cosine-fit residuals.
    `saturation_dn` is the clipping level (default: the dtype maximum for integer frames);
    samples within `options.saturation_margin` of it are excluded as clipped.
    """

    def __init__(
        self,
        plan: Plan,
        shape: tuple[int, int],
        *,
        noise: NoiseModel | NoiseSource | float | None = None,
        saturation_dn: float | None = None,
        options: DecodeOptions | None = None,
        xp: ModuleType | str | None = np,
    ) -> None:
        self.plan = plan
        self.options = options or DecodeOptions()
        self.xp = array_module(xp)
        self._variance = variance_function(noise)
        constant = isinstance(noise, int | float)
        self._noise_kind = "residual" if noise is None else "constant" if constant else "model"
        self._acc = FrameAccumulator(
            plan,
            shape,
            saturation_dn=saturation_dn,
            saturation_margin=self.options.saturation_margin,
            need_squares=self._variance is None,
            xp=self.xp,
        )
        self._finished = False
        self._ptc: LinearVariance | None = None
        self._leak: Any = None  # per set r^2 of the display harmonic in the residuals
        # Large NumPy images may take the compiled per-pixel kernel; other namespaces (CuPy)
        # the array-namespace path.
        self._large = self.xp is np and int(shape[0]) * int(shape[1]) >= _COMPILED_MIN_PIXELS

    @property
    def missing(self) -> list[int]:
        """Plan indices still needed before `finish`."""
        return self._acc.missing

    def prepare(self) -> None:
        """Load the compiled finish kernel now, for images of >= 1 Mpixel (a live capture
        calls this while frames arrive). Loading it costs ~1 s of CPU (numba's import and
        its cached machine code), more than it saves on one 5 Mpixel finish, so a decoder
        uses it only once it is loaded in the process (long-lived workers, live captures)."""
        if self._large:
            from calibration.decode.kernel import warm_up

            warm_up()

    @property
    def _compiled(self) -> bool:
        """Finish with the compiled kernel: a large NumPy image and the kernel loaded."""
        return self._large and "calibration.decode.kernel" in sys.modules

    def add(self, index: int, image: np.ndarray) -> None:
        """Fold plan frame `index` into the running sums (any order, each index once)."""
        if self._finished:
            raise DecodeError(f"frame {index}: the decoder has already finished")
        self._acc.add(index, image)

    # -- finishing ---------------------------------------------------------------------
    def finish(self, meta: dict[str, Any] | None = None) -> DecodedMaps:
        """Decode the accumulated frames into `DecodedMaps` (raises `DecodeError` if unusable)."""
        acc = self._acc
        missing = acc.missing
        if missing:
            raise DecodeError(
                f"frames: {len(missing)} plan frame(s) missing, first {missing[:10]}; "
                "every cosine and flat frame of the plan is needed"
            )
        self._finished = True
        h, w = acc.shape
        npix = h * w
        axes = self.plan.axes()
        # Chunks write every pixel of the plan's axes: no NaN pre-fill there (first-touch
        # page faults of ~300 MB of outputs then happen in the worker threads, in parallel).
        planes = _output_planes(npix, axes) if self._compiled else None
        if planes is not None:
            out = {f"{kind}{axis}": planes[kind.rstrip("_") or "position"][row]
                   for row, axis in enumerate(("x", "y"))
                   for kind in ("", "sigma_", "modulation_", "blur_")}
        else:
            nan_filled = functools.partial(np.full, fill_value=np.nan)
            out = {
                f"{kind}{axis}": (np.empty if axis in axes else nan_filled)(
                    npix, dtype=np.float64 if kind == "" else np.float32
                )
                for axis in ("x", "y")
                for kind in ("", "sigma_", "modulation_", "blur_")
            }
        reason = np.zeros(npix, dtype=np.uint8)
        step = self.options.chunk_pixels
        if self._variance is None:
            self._estimate_noise(npix)
        chunks = [slice(s, min(s + step, npix)) for s in range(0, npix, step)]
        self._map(lambda sl: self._finish_chunk(sl, out, planes, reason), chunks)
        mark_screen_edges(reason.reshape(h, w))
        counts = {name: int((reason == code).sum()) for code, name in enumerate(REASONS)}
        if counts["valid"] == 0:
            raise DecodeError(self._no_valid_message(counts, npix))
        mask = reason == 0
        for key in ("x", "y", "sigma_x", "sigma_y", "blur_x", "blur_y"):
            out[key][~mask] = np.nan
        info = {
            "format": MAPS_FORMAT,
            "plan_digest": self.plan.digest(),
            "software": f"phasecal {_software_version()}",
            "decoder": {
                "noise": self._noise_kind,
                "photon_transfer": asdict(self._ptc) if self._ptc is not None else None,
                "display_harmonic_r2": self._leak,
                "clip_threshold_dn": acc.high,
                "max_sample_dn": acc.max_seen if math.isfinite(acc.max_seen) else None,
                "frame_dtype": str(acc.dtype),
                "options": asdict(self.options),
            },
            "pixel_counts": counts,
        }
        info.update(meta or {})
        shaped = {k: v.reshape(h, w) for k, v in out.items()}
        return DecodedMaps(
            x=shaped["x"],
            y=shaped["y"],
            sigma_x=shaped["sigma_x"],
            sigma_y=shaped["sigma_y"],
            mask=mask.reshape(h, w),
            modulation_x=shaped["modulation_x"],
            modulation_y=shaped["modulation_y"],
            blur_x=shaped["blur_x"] if "x" in axes else None,
            blur_y=shaped["blur_y"] if "y" in axes else None,
            meta=info,
        )

    def _map(self, fn: Callable[[slice], None], chunks: list[slice]) -> None:
        """Run `fn` on disjoint pixel chunks; NumPy releases the GIL, so threads use the cores."""
        workers = min(len(chunks), os.cpu_count() or 1, 4) if self.xp is np else 1
        if workers <= 1:
            for sl in chunks:
                fn(sl)
            return
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(fn, chunks))

    def _no_valid_message(self, counts: dict[str, int], npix: int) -> str:
        """One line saying why no pixel could be decoded."""
        worst = max((n, name) for name, n in counts.items() if name != "valid")[1]
        if counts["no_screen"] == npix:
            return (
                "frames: no pixel sees the screen (the bright flat is nowhere brighter than "
                "the dark flat beyond the noise): all-dark stack, display off or lens capped?"
            )
        return f"frames: no pixel could be decoded; most common reason: {worst} ({counts})"

    def _residuals(self, fits: list[SetFit], sl: slice) -> tuple[Any, Any, Any]:
        """Per-pixel residual sum of squares, its degrees of freedom and their noise level.

        The level is the dof-weighted average of the sets' residual levels (`SetFit.level`),
        so with variance linear in the level, `E[rss/dof] = offset + slope * level` holds
        exactly, also for pixels whose bright steps clipped.
        """
        xp = self.xp
        rss = self._acc.squares.reshape(-1)[sl].astype(xp.float64)
        dof = xp.zeros_like(rss)
        level = xp.zeros_like(rss)
        for f, s, r2 in zip(fits, self._acc.sets, self._leak or [0.0] * len(fits), strict=True):
            rss = rss - xp.where(f.ok, f.explained, 0.0)
            if r2:  # the display harmonic in the residual is not noise (`harmonic_leak`)
                rss = rss - r2 * nyquist_power(xp, [f], [s])[0]
            dof = dof + xp.where(f.ok, f.dof, 0.0)
            level = level + xp.where(f.ok, f.dof * f.level, 0.0)
        return xp.maximum(rss, 0.0), dof, level / xp.maximum(dof, 1.0)

    def _estimate_noise(self, npix: int) -> None:
        """Residual mode: fit a photon-transfer line to the pixels' residuals (first pass),
        on the pixels `line_pixels` chooses, held at or above the floor from the median
        dark-flat level up (the lowest level the sensor records there), less the display
        harmonic that falls into the residual (`harmonic_leak`)."""
        acc = self._acc
        pieces = sample_pieces(npix, self.options.chunk_pixels, _NOISE_PIECE, _NOISE_SAMPLE)
        size = sum(sl.stop - sl.start for sl in pieces)
        mean, rss, dof, span, dark = (np.empty(size, dtype=np.float32) for _ in range(5))
        power = np.empty((len(acc.sets), size), dtype=np.float32)
        clean, no_dark_clip = np.empty(size, dtype=bool), np.empty(size, dtype=bool)
        offsets = np.cumsum([0] + [sl.stop - sl.start for sl in pieces])

        def one(k: int) -> None:
            sl, to = pieces[k], slice(int(offsets[k]), int(offsets[k + 1]))
            skip = self._sees_no_screen(sl)
            fits = [fit_set(self.xp, s, sl, residuals=True, skip=skip) for s in acc.sets]
            r, d, m = self._residuals(fits, sl)
            rss[to], dof[to], mean[to] = to_host(r), to_host(d), to_host(m)
            power[:, to] = to_host(self.xp.stack(nyquist_power(self.xp, fits, acc.sets)))
            dark[to] = to_host(acc.dark.reshape(-1)[sl] / acc.n_dark)
            span[to] = to_host(acc.bright.reshape(-1)[sl] / acc.n_bright) - dark[to]
            clean[to] = to_host(~functools.reduce(lambda x, y: x | y, [f.clipped for f in fits]))
            low = functools.reduce(lambda x, y: x | y, [f.low_clipped for f in fits])
            no_dark_clip[to] = to_host(~low)

        self._map(one, list(range(len(pieces))))
        spread = ~undithered(span, rss, dof, no_dark_clip, quantized=acc.dtype.kind == "u")
        use = line_pixels(clean, no_dark_clip, spread, dof, _MIN_CLEAN_PIXELS)
        self._ptc, self._leak = residual_line(mean[use], rss[use], dof[use], power[:, use],
                                              self._floor, dark[use])

    def _sees_no_screen(self, sl: slice) -> Any:
        """Pixels whose flat contrast fails `min_contrast_snr` even at the smallest credible
        noise (the floor): `no_screen` whatever the noise estimate, so their clipped steps
        (a dark surround reading 0 DN) need no least-squares fit, the costliest part."""
        acc = self._acc
        bright = acc.bright.reshape(-1)[sl] / acc.n_bright
        dark = acc.dark.reshape(-1)[sl] / acc.n_dark
        floor_sigma = math.sqrt(self._floor * (1.0 / acc.n_bright + 1.0 / acc.n_dark))
        return ~((bright - dark) >= self.options.min_contrast_snr * floor_sigma)

    @property
    def _floor(self) -> float:
        """Smallest credible sample variance: quantization of integer frames."""
        return 1.0 / 12.0 if self._acc.dtype.kind == "u" else 1e-12

    def _noise_variances(self, fits: list[SetFit], sl: slice) -> tuple[list[Any], VarianceFn]:
        """Per-set sample variance (DN^2) for this chunk, and the variance function for flats.

        With a given noise model it is evaluated at each period's mean level. In residual
        mode the fitted photon-transfer line is used, except at pixels whose own residuals
        exceed it beyond a 1e-6 chi-square tail (a model error there): those keep their
        own, larger residual variance.
        """
        xp = self.xp
        if self._variance is not None:
            fn = self._variance
            per_set = [fn(phase_level(xp, f, s, sl)) for f, s in zip(fits, self._acc.sets,
                                                                      strict=True)]
            everywhere = xp.ones(fits[0].mean.shape, dtype=bool)
            for f, var in zip(fits, per_set, strict=True):
                f.use_step_levels(xp, fn, var, everywhere)
            return per_set, fn
        rss, dof, _ = self._residuals(fits, sl)
        own = xp.where(dof > 0, xp.maximum(rss / xp.maximum(dof, 1.0), self._floor), xp.nan)
        if self._ptc is None:
            return [own] * len(fits), lambda level: own
        ptc = self._ptc.variance
        limit = xp.asarray(_chi2_tail(int(to_host(dof).max()) if dof.size else 0))
        excess = own > ptc(xp.maximum(fits[0].mean, 0.0)) * limit[dof.astype(xp.int64)]
        per_set = [xp.where(excess, own, ptc(phase_level(xp, f, s, sl)))
                   for f, s in zip(fits, self._acc.sets, strict=True)]
        for f, var in zip(fits, per_set, strict=True):
            f.use_step_levels(xp, ptc, var, ~excess)
        return per_set, ptc  # the flats are not subject to the cosine-fit model error

    def _finish_chunk(self, sl: slice, out: dict, planes: dict | None,
                      reason: np.ndarray) -> None:
        """Decode one flattened pixel range into `out` (or `planes`) and `reason`."""
        xp, acc = self.xp, self._acc
        skip = self._sees_no_screen(sl)
        fits = [fit_set(xp, s, sl, residuals=self._variance is None, skip=skip)
                for s in acc.sets]
        variances, level_var = self._noise_variances(fits, sl)
        bright = acc.bright.reshape(-1)[sl] / acc.n_bright
        dark = acc.dark.reshape(-1)[sl] / acc.n_dark
        var_b, var_d = level_var(bright), level_var(xp.maximum(dark, 0.0))
        contrast_var = var_b / acc.n_bright + var_d / acc.n_dark
        contrast_snr = (bright - dark) / xp.sqrt(contrast_var)
        contrast_snr = xp.where(xp.isfinite(contrast_snr), contrast_snr, 0.0)
        if planes is not None:
            reason[sl] = decode_axes_compiled(self.plan, acc.sets, fits, variances,
                                              contrast_snr, self.options, planes, sl)
        else:
            reason[sl] = decode_axes_xp(xp, self.plan, acc.sets, fits, variances, contrast_snr,
                                        self.options, out, sl)


def decode_stack(
    plan: Plan,
    frames: Any,
    *,
    noise: NoiseModel | NoiseSource | float | None = None,
    saturation_dn: float | None = None,
    options: DecodeOptions | None = None,
    xp: ModuleType | str | None = np,
    meta: dict[str, Any] | None = None, progress: ProgressFn | None = None,
    cancelled: CancelCheck | None = None, prepare: bool = False,
) -> DecodedMaps:
    """The one decode loop: frames in plan order (an (F, H, W) stack, a `FrameSource` or any
    sized iterable of 2-D frames) to maps; progress per frame, `Cancelled` between frames."""
    count = len(frames)
    if count != len(plan.frames):
        raise DecodeError(f"frames: {count} frames given, the plan has {len(plan.frames)} "
                          "(frame i must be captured while plan frame i was shown)")
    dec: StreamingDecoder | None = None
    for i, frame in enumerate(frames):
        if cancelled is not None and cancelled():
            raise Cancelled(f"decode cancelled after {i} of {count} frames")
        if dec is None:
            if getattr(frame, "ndim", None) != 2:
                raise DecodeError("frames: expected a (F, H, W) stack of single-channel frames, "
                                  f"got frame shape {getattr(frame, 'shape', None)}")
            dec = StreamingDecoder(plan, tuple(frame.shape), noise=noise,
                                   saturation_dn=saturation_dn, options=options, xp=xp)
            if prepare:
                dec.prepare()
        dec.add(i, frame)
        if progress is not None:
            progress(i + 1, count, "decode")
    assert dec is not None  # count == len(plan.frames) > 0
    if progress is not None:
        progress(count, count, "unwrap")
    return dec.finish(meta)
