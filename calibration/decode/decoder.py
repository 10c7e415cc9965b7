"""`StreamingDecoder`: frames in (any order), `phasecal.maps/1` decoded maps out.

The per-frame work is only the accumulation (accumulate.py); `finish` fits each period
(phase.py), estimates the noise, unwraps (unwrap.py), fits blur (blur.py) and applies the
validity rules (validity.py), chunk by chunk over the pixels to bound temporary memory.
"""

from __future__ import annotations

import functools
import math
import sys
from collections.abc import Callable, Iterator
from dataclasses import asdict
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

from calibration.decode import sums_cache
from calibration.decode.accumulate import DecodeError, FrameAccumulator
from calibration.decode.arrays import array_module, to_host
from calibration.decode.axes import decode_axes_compiled, decode_axes_xp
from calibration.decode.batch import (
    ChunkSums,
    StackPass,
    add_frames,
    chunk_view,
    in_parallel,
)
from calibration.decode.dark_chunks import write_dark_range
from calibration.decode.finish import (
    FinishInputs,
    chi2_tail,
    finish_range,
    noise_params,
    output_planes,
    residual_stats,
)
from calibration.decode.noise import (
    LinearVariance,
    NoiseModel,
    NoiseSource,
    VarianceFn,
    line_sample,
    nyquist_power,
    phase_level,
    residual_line,
    sample_pieces,
    variance_function,
)
from calibration.decode.options import DecodeOptions
from calibration.decode.phase import SetFit, fit_set
from calibration.decode.validity import FinalRows, hide_invalid
from calibration.shared.maps import MAPS_FORMAT, DecodedMaps
from calibration.shared.plan import Plan

if TYPE_CHECKING:  # (a numba module: loaded only with the compiled path)
    from calibration.decode.kernel_clipped import PatternTables

# The photon-transfer fit uses only pixels without clipped steps when at least this many exist.
_MIN_CLEAN_PIXELS = 2000
_DARK_PROBE = 64  # the stride of `_finish_dark_range`'s first look at a range
# Larger images fit the photon-transfer line on evenly spread pieces of this many pixels,
# about _NOISE_SAMPLE in all (the fit needs ~1e5 pixels; more costs time, twice in finish_stack).
_NOISE_PIECE = 1 << 14
_NOISE_SAMPLE = 1 << 19
# Images of at least this many pixels take the compiled kernels once loaded (below, a
# one-off process spends more loading them than they save); public: a service worker
# prepares its heap for the compiled path by the same rule (api.worker.tasks).
COMPILED_MIN_PIXELS = 1 << 20
# One-off decodes (decode_stack: `one_shot_compiled`) of images this large load the compiled
# kernels (~0.15 CPU s once per process, numba's start included) even when no live capture
# has loaded them yet: they pay back (with the noise given: 1280x1024 0.33 CPU s against
# 0.58 for NumPy; 640x480 0.25-0.36 against 0.17-0.24).
ALWAYS_COMPILED_PIXELS = 1 << 20
# With the noise estimated from the residuals numba is loaded anyway (the photon-transfer
# line's kernels), and the compiled decode pays back from small images on (320x240: 0.27
# CPU s against 0.31; 1280x1024: 0.53 against 1.6).
RESIDUAL_COMPILED_PIXELS = 1 << 16
_KERNELS = ("calibration.decode.kernel_sums", "calibration.decode.accumulate_kernel")


def one_shot_compiled(pixels: int, noise: object) -> bool:
    """Whether a one-off decode of `pixels`-pixel frames (noise model `noise`, None: from the
    residuals) loads the compiled kernels rather than taking the NumPy path."""
    return pixels >= (RESIDUAL_COMPILED_PIXELS if noise is None else ALWAYS_COMPILED_PIXELS)


@functools.lru_cache(maxsize=1)
def _software_version() -> str:
    """Installed phasecal version, or 'unknown' when running from a bare checkout (looked up
    once: the lookup reads the installed packages' metadata, ~3 ms a finish)."""
    try:
        from importlib.metadata import version

        return version("phasecal")
    except Exception:
        return "unknown"


def _no_valid_message(counts: dict[str, int], npix: int) -> str:
    """One line saying why no pixel could be decoded."""
    worst = max((n, name) for name, n in counts.items() if name != "valid")[1]
    if counts["no_screen"] == npix:
        return (
            "frames: no pixel sees the screen (the bright flat is nowhere brighter than "
            "the dark flat beyond the noise): all-dark stack, display off or lens capped?"
        )
    return f"frames: no pixel could be decoded; most common reason: {worst} ({counts})"


class StreamingDecoder:
    """Accepts one pose's frames one at a time (`add`), then decodes them (`finish`).

    Implements `acquisition.sinks.FrameSink`. `noise` is the per-frame camera noise: a
    `NoiseModel`, any object with `noise_sigma_dn(mean)` (e.g. a sensor model), a constant
    sigma in DN, or None to estimate it per pixel from the cosine-fit residuals.
    `saturation_dn` is the clipping level (default: the dtype maximum for integer frames);
    samples within `options.saturation_margin` of it are excluded as clipped.
    `compiled`: use the compiled kernels (loaded by `prepare`) also below 1 Mpixel, where a
    one-off process would spend more loading them than they save: for long-lived workers.
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
        compiled: bool = False,
    ) -> None:
        self.plan = plan
        self.options = options or DecodeOptions()
        self.xp = array_module(xp)
        self._noise = noise
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
        # Large NumPy images (any size with `compiled`: a long-lived live worker) may take the
        # compiled per-pixel kernel; other namespaces (CuPy) the array-namespace path.
        self.uses_kernels = self.xp is np and (
            compiled or int(shape[0]) * int(shape[1]) >= COMPILED_MIN_PIXELS)
        self._acc.compiled = self.compiled_now

    @property
    def missing(self) -> list[int]:
        """Plan indices still needed before `finish`."""
        return self._acc.missing

    def prepare(self) -> None:
        """Load the compiled kernels now (>= 1 Mpixel, or `compiled`; ~0.7 s of CPU: a decoder
        uses them only once loaded in the process) and allocate the sums (a live capture
        calls this before frames arrive)."""
        if self.uses_kernels:
            from calibration.decode.kernel_warm import warm_up

            warm_up()
            self._acc.compiled = self.compiled_now
        if self.xp is np:  # in a long-lived process: an earlier decode's sums, zeroed again
            self._acc.take = sums_cache.take
        self._acc.allocate()

    def release(self) -> None:
        """Give the sums to the next decoder of this process (`sums_cache`); not used again."""
        acc, self._finished = self._acc, True
        sums_cache.keep([acc.block, acc.bright, acc.dark, acc.squares])
        acc.block = acc.bright = acc.dark = acc.squares = None

    @property
    def compiled_now(self) -> bool:
        """Whether frames added now are accumulated, and a finish now decodes, with the
        compiled kernels: `uses_kernels` and the kernels' modules loaded in the process
        (by `prepare`, or by `decode_stack` for a whole stack)."""
        return self.uses_kernels and all(name in sys.modules for name in _KERNELS)

    def add(self, index: int, image: np.ndarray) -> None:
        """Fold plan frame `index` into the running sums (any order, each index once)."""
        self.add_frames([index], [image])

    def ready_frames(self, available: Any) -> list[int]:
        """Of the plan indices `available` (stored, not yet added), those worth adding now:
        flats and whole period groups (one cache-blocked pass per group, not one per frame);
        once one group is left, its frames as they come (one frame's pass after the last)."""
        return self._acc.ready_frames(available)

    def add_frames(self, indices: list[int], stack: Any, rows: list[int] | None = None) -> None:
        """Fold several frames at once: `stack[rows[j]]` (default `stack[j]`) is plan frame
        `indices[j]`. The compiled path reads each frame once, in cache blocks: a live
        decoder catching up on a frame store's new frames pays one pass for all of them."""
        if self._finished:
            raise DecodeError(f"frames {list(indices)[:10]}: the decoder has already finished")
        if self.compiled_now:
            self._acc.compiled = True
            add_frames(self._acc, indices, stack, rows)
            return
        for j, index in enumerate(indices):
            self._acc.add(index, stack[j if rows is None else rows[j]])

    # -- finishing ---------------------------------------------------------------------
    def finish(self, meta: dict[str, Any] | None = None,
               into: dict[str, np.ndarray] | None = None,
               final_rows: Callable[[int], None] | None = None) -> DecodedMaps:
        """Decode the accumulated frames into `DecodedMaps` (`DecodeError` if unusable), into
        the arrays `into` if given (`calibration.shared.maps_file.MapsFile.outputs`);
        `final_rows(rows)` hears, while later rows still decode, how many leading rows of
        the outputs will not change again (`MapsFile.write_rows`)."""
        acc = self._acc
        missing = acc.missing
        if missing:
            raise DecodeError(
                f"frames: {len(missing)} plan frame(s) missing, first {missing[:10]}; "
                "every cosine and flat frame of the plan is needed"
            )
        self._finished = True
        acc.allocate()  # (a plan of flats only: nothing was added)
        return self._decode(lambda sl: chunk_view(acc, sl), meta, into=into,
                            final_rows=final_rows)

    def finish_stack(self, stack: np.ndarray, meta: dict[str, Any] | None = None,
                     step: Callable[[float], None] | None = None,
                     into: dict[str, np.ndarray] | None = None) -> DecodedMaps:
        """Decode a whole (F, H, W) stack in plan order (compiled path, nothing added yet):
        each pixel range's sums are accumulated right before it is finished, so no
        full-image sums exist (no page faults for them) and each frame byte is read once.
        `step(fraction)` runs between groups of ranges (progress, cancellation); `into` as
        for `finish`."""
        acc = self._acc
        if self._finished or acc.added.any():
            raise DecodeError("frames: finish_stack needs a fresh decoder")
        for i in range(stack.shape[0]):
            acc.check(i, stack[i])
        self._finished = True
        flat = stack.reshape(stack.shape[0], -1)
        if not flat.flags.c_contiguous:
            flat = np.ascontiguousarray(flat)
        whole = StackPass(acc, flat)  # frame counts are known from the plan
        return self._decode(whole.sums, meta, step, whole.done, into)

    def _decode(self, chunk_of: Callable[[slice], ChunkSums], meta: dict[str, Any] | None,
                step: Callable[[float], None] | None = None,
                summed: Callable[[], None] | None = None,
                into: dict[str, np.ndarray] | None = None,
                final_rows: Callable[[int], None] | None = None) -> DecodedMaps:
        """Noise estimate, then every pixel range's finish; `chunk_of` gives a range's sums,
        `into` the output planes and mask (else new arrays), `final_rows` as for `finish`."""
        acc = self._acc
        h, w = acc.shape
        npix = h * w
        axes = self.plan.axes()
        # Chunks write every pixel of the plan's axes: no NaN pre-fill there (first-touch
        # page faults of new outputs then happen in the worker threads, in parallel).
        planes = output_planes(npix, axes, into)
        out = {f"{kind}{axis}": planes[kind.rstrip("_") or "position"][row]
               for row, axis in enumerate(("x", "y"))
               for kind in ("", "sigma_", "modulation_", "blur_")}
        kernel_planes = planes if self.compiled_now else None
        reason = np.zeros(npix, dtype=np.uint8)
        mask = np.empty(npix, dtype=bool) if into is None else into["mask"]
        size = self.options.chunk_pixels
        if self._variance is None:
            self._estimate_noise(npix, chunk_of)
        inputs = self._finish_inputs() if kernel_planes is not None else None
        chunks = [slice(s, min(s + size, npix)) for s in range(0, npix, size)]
        group = max(1, len(chunks) // 16) if step is not None else len(chunks)
        tallies: list[np.ndarray] = []
        final = FinalRows(reason.reshape(h, w), mask, out, final_rows)
        for g in range(0, len(chunks), group):
            part = chunks[g:g + group]
            done = self._in_order(lambda sl: self._finish_chunk(
                chunk_of(sl), sl, out, inputs, kernel_planes, reason, mask), part)
            for sl, tally in zip(part, done, strict=True):
                tallies.append(tally)
                final.decoded(sl.stop)  # (ranges in pixel order: rows final behind them)
            if step is not None:
                step(min(g + group, len(chunks)) / len(chunks))
        if summed is not None:
            summed()
        counts = final.counts(tallies)
        if counts["valid"] == 0:
            raise DecodeError(_no_valid_message(counts, npix))
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
        """Run `fn` on disjoint pixel chunks (`_in_order`, results dropped)."""
        for _ in self._in_order(fn, chunks):
            pass

    def _in_order(self, fn: Callable[[slice], Any], chunks: list[slice]) -> Iterator[Any]:
        """`fn`'s results on disjoint pixel chunks, in the chunks' order as they come: from
        the shared pool (NumPy and the kernels release the GIL, so threads use the cores),
        one after another for other namespaces."""
        if self.xp is np:
            return in_parallel(fn, chunks)
        return map(fn, chunks)

    def _residuals(self, fits: list[SetFit], chunk: ChunkSums) -> tuple[Any, Any, Any]:
        """Per-pixel residual sum of squares, its degrees of freedom and their noise level.

        The level is the dof-weighted average of the sets' residual levels (`SetFit.level`),
        so with variance linear in the level, `E[rss/dof] = offset + slope * level` holds
        exactly, also for pixels whose bright steps clipped.
        """
        xp = self.xp
        rss = chunk.squares.astype(xp.float64)
        dof = xp.zeros_like(rss)
        level = xp.zeros_like(rss)
        for f, s, r2 in zip(fits, chunk.sets, self._leak or [0.0] * len(fits), strict=True):
            rss = rss - xp.where(f.ok, f.explained, 0.0)
            if r2:  # the display harmonic in the residual is not noise (`harmonic_leak`)
                rss = rss - r2 * nyquist_power(xp, [f], [s])[0]
            dof = dof + xp.where(f.ok, f.dof, 0.0)
            level = level + xp.where(f.ok, f.dof * f.level, 0.0)
        return xp.maximum(rss, 0.0), dof, level / xp.maximum(dof, 1.0)

    def _estimate_noise(self, npix: int, chunk_of: Callable[[slice], ChunkSums]) -> None:
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
        inputs = self._finish_inputs() if self.compiled_now else None

        def one(k: int, lazy: bool) -> None:
            to, chunk = slice(int(offsets[k]), int(offsets[k + 1])), chunk_of(pieces[k])
            stats = (self._residual_arrays(chunk) if inputs is None
                     else self._residual_stats(inputs, chunk, lazy))
            mean[to], rss[to], dof[to], clean[to], no_dark_clip[to], power[:, to] = stats
            dark[to] = to_host(chunk.dark / acc.n_dark)
            span[to] = to_host(chunk.bright / acc.n_bright) - dark[to]

        use = np.flatnonzero(line_sample(
            lambda lazy: self._map(lambda k: one(k, lazy), list(range(len(pieces)))),
            clean, no_dark_clip, span, rss, dof, _MIN_CLEAN_PIXELS, acc.dtype))
        # (`take` by index: a few ms less than five boolean selections, on the main thread)
        self._ptc, self._leak = residual_line(mean.take(use), rss.take(use), dof.take(use),
                                              power.take(use, axis=1), self._floor,
                                              dark.take(use))

    def _sees_no_screen(self, chunk: ChunkSums, every: int = 1) -> Any:
        """Pixels (each `every`-th) whose flat contrast fails `min_contrast_snr` even at the
        smallest credible noise (the floor): `no_screen` whatever the noise estimate, so
        their clipped steps (a dark surround reading 0 DN) need no least-squares fit, the
        costliest part."""
        acc = self._acc
        bright, dark = chunk.bright[::every] / acc.n_bright, chunk.dark[::every] / acc.n_dark
        floor_sigma = math.sqrt(self._floor * (1.0 / acc.n_bright + 1.0 / acc.n_dark))
        return ~((bright - dark) >= self.options.min_contrast_snr * floor_sigma)

    @property
    def _floor(self) -> float:
        """Smallest credible sample variance: quantization of integer frames."""
        return 1.0 / 12.0 if self._acc.dtype.kind == "u" else 1e-12

    def _noise_variances(self, fits: list[SetFit], chunk: ChunkSums
                         ) -> tuple[list[Any], VarianceFn]:
        """Per-set sample variance (DN^2) for this chunk, and the variance function for flats.

        With a given noise model it is evaluated at each period's mean level. In residual
        mode the fitted photon-transfer line is used, except at pixels whose own residuals
        exceed it beyond a 1e-6 chi-square tail (a model error there): those keep their
        own, larger residual variance.
        """
        xp = self.xp
        if self._variance is not None:
            fn = self._variance
            per_set = [fn(phase_level(xp, f, s, slice(None)))
                       for f, s in zip(fits, chunk.sets, strict=True)]
            everywhere = xp.ones(fits[0].mean.shape, dtype=bool)
            for f, var in zip(fits, per_set, strict=True):
                f.use_step_levels(xp, fn, var, everywhere)
            return per_set, fn
        rss, dof, _ = self._residuals(fits, chunk)
        own = xp.where(dof > 0, xp.maximum(rss / xp.maximum(dof, 1.0), self._floor), xp.nan)
        if self._ptc is None:
            return [own] * len(fits), lambda level: own
        ptc = self._ptc.variance
        limit = xp.asarray(chi2_tail(int(to_host(dof).max()) if dof.size else 0))
        excess = own > ptc(xp.maximum(fits[0].mean, 0.0)) * limit[dof.astype(xp.int64)]
        per_set = [xp.where(excess, own, ptc(phase_level(xp, f, s, slice(None))))
                   for f, s in zip(fits, chunk.sets, strict=True)]
        for f, var in zip(fits, per_set, strict=True):
            f.use_step_levels(xp, ptc, var, ~excess)
        return per_set, ptc  # the flats are not subject to the cosine-fit model error

    def _finish_chunk(self, chunk: ChunkSums, sl: slice, out: dict,
                      inputs: FinishInputs | None, planes: dict | None, reason: np.ndarray,
                      mask: np.ndarray) -> np.ndarray:
        """Decode one flattened pixel range into `out` (or, compiled: `planes`), `reason`
        and `mask`; returns its tally of reason codes (`hide_invalid`)."""
        if inputs is None or planes is None:
            reason[sl] = self._finish_arrays(chunk, sl, out=out)
        elif not self._finish_dark_range(chunk, sl, planes, reason):  # a dark surround
            self._finish_range(inputs, chunk, sl, planes, reason)
        return hide_invalid(out, mask, reason, sl)

    def _finish_dark_range(self, chunk: ChunkSums, sl: slice, planes: dict[str, np.ndarray],
                           reason: np.ndarray) -> bool:
        """If no pixel of `sl` clipped a step and every one fails the flat-contrast test even
        at the smallest credible noise (`_sees_no_screen`), write what the compiled finish
        would (`write_dark_range`) and return True; False leaves the range to the kernel.

        Only in residual-noise mode, where the kernel's flat variances (the photon-transfer
        line or the pixel's own residual) are never below that floor; a given noise may be."""
        if self._variance is not None or (chunk.bits is not None and chunk.bits.any()):
            return False
        # (a probe of every `_DARK_PROBE`-th pixel first: a lit range, most of them, is told
        # from a few hundred pixels, not after the whole range's arithmetic)
        if not (self._sees_no_screen(chunk, _DARK_PROBE).all()
                and self._sees_no_screen(chunk).all()):
            return False
        write_dark_range(chunk, sl, planes, reason)
        return True

    def _finish_range(self, inputs: FinishInputs, chunk: ChunkSums, sl: slice,
                      planes: dict[str, np.ndarray], reason: np.ndarray) -> None:
        """The compiled finish of the range `sl` (`finish_range`), then the pixels it left
        by the array path, on a gathered copy of their sums."""
        dirty = finish_range(inputs, chunk, sl, planes, reason)
        if dirty.size == 0:
            return
        sub = output_planes(dirty.size, self.plan.axes())
        reason[sl][dirty] = self._finish_arrays(chunk.take(dirty), slice(None), planes=sub)
        for name, arr in sub.items():
            planes[name][:, sl][:, dirty] = arr

    def _residual_stats(self, inputs: FinishInputs, chunk: ChunkSums, lazy: bool
                        ) -> tuple[np.ndarray, ...]:
        """(level, rss, dof, clean, no_dark_clip, power) of a range for the noise line by
        the compiled pass (`residual_stats`), the pixels it left by the array path."""
        stats, left = residual_stats(inputs, chunk, lazy)
        if left.size:
            for arr, part in zip(stats, self._residual_arrays(chunk.take(left)), strict=True):
                arr[..., left] = part
        return stats

    def _residual_arrays(self, chunk: ChunkSums) -> tuple[np.ndarray, ...]:
        """(level, rss, dof, clean, no_dark_clip, power) of a range for the noise line by the
        array path (every pixel fitted), as host arrays."""
        xp = self.xp
        fits = [fit_set(xp, s, slice(None), residuals=True, skip=self._sees_no_screen(chunk))
                for s in chunk.sets]
        r, d, m = self._residuals(fits, chunk)
        clean = ~functools.reduce(lambda x, y: x | y, [f.clipped for f in fits])
        low = functools.reduce(lambda x, y: x | y, [f.low_clipped for f in fits])
        power = xp.stack(nyquist_power(xp, fits, chunk.sets))
        return tuple(to_host(v) for v in (m, r, d, clean, ~low, power))

    def _finish_inputs(self) -> FinishInputs:
        """What the compiled passes read of this decoder now (`FinishInputs`): the noise
        parameters and harmonic leak as known at this point of the decode."""
        leak = np.zeros(len(self._acc.sets)) if self._leak is None else np.asarray(
            self._leak, float)
        return FinishInputs(self._acc, self.plan, self.options, self._floor,
                            noise_params(self._noise, self._ptc, self._floor), leak,
                            self._pattern_tables)

    @functools.cached_property
    def _pattern_tables(self) -> PatternTables | None:
        """The least-squares tables of the clipped patterns this decoder's ranges meet
        (grown as they are met; None for plans of > 16 steps)."""
        from calibration.decode.kernel_clipped import pattern_tables  # (compiled path only)

        return pattern_tables(self._acc.sets)

    def _finish_arrays(self, chunk: ChunkSums, sl: slice, out: dict | None = None,
                       planes: dict | None = None) -> np.ndarray:
        """Array path of one range: outputs into `out[..][sl]` or `planes[..][:, sl]`;
        returns its reason codes."""
        xp, acc = self.xp, self._acc
        skip = self._sees_no_screen(chunk)
        fits = [fit_set(xp, s, slice(None), residuals=self._variance is None, skip=skip)
                for s in chunk.sets]
        variances, level_var = self._noise_variances(fits, chunk)
        bright, dark = chunk.bright / acc.n_bright, chunk.dark / acc.n_dark
        var_b, var_d = level_var(bright), level_var(xp.maximum(dark, 0.0))
        contrast_var = var_b / acc.n_bright + var_d / acc.n_dark
        contrast_snr = (bright - dark) / xp.sqrt(contrast_var)
        contrast_snr = xp.where(xp.isfinite(contrast_snr), contrast_snr, 0.0)
        if planes is not None:
            return decode_axes_compiled(self.plan, acc.sets, fits, variances, contrast_snr,
                                        self.options, planes, sl)
        return decode_axes_xp(xp, self.plan, acc.sets, fits, variances, contrast_snr,
                              self.options, out, sl)

