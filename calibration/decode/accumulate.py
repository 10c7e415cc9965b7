"""Running per-pixel sums of one pose's frames: O(pixels x periods) memory, frames in any order.

For each (axis, period) set it keeps `a = sum v sin(psi)`, `b = sum v cos(psi)`,
`s0 = sum v` (float32) and, only once a clipped sample appears, a per-pixel bit mask of
the excluded steps (their values are zeroed before summing, so the sums cover the kept
steps; the phase fit then solves the least-squares problem of the kept steps). A single
pose-wide `sum v^2` (only when the noise is estimated from residuals) and the averaged
bright/dark flats complete the state.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

import numpy as np

from calibration.shared.plan import CosineFrame, FlatFrame, Plan

try:  # OpenCV's fused SIMD kernels accumulate uint8/uint16 into float32 without temporaries.
    import cv2
except ImportError:  # pragma: no cover - opencv is a project dependency
    cv2 = None

ACCEPTED_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))


def harmonic_orders(steps: int, residual_noise: bool) -> tuple[int, ...]:
    """Harmonics above the fundamental that the per-period fit also models.

    Display gamma puts ~30 % of the fundamental into harmonic 2 and ~1 % into harmonic 3.
    They are orthogonal to the fundamental over all steps, but leak into the phase when
    clipped steps are excluded and inflate the residual noise estimate. Harmonic 2 is
    modelled from 6 steps on; harmonic 3 (residual-noise mode only) from 8. Each keeps
    at least one residual degree of freedom and stays below the Nyquist order. Fits on
    partial steps model harmonic 2 at most (`phase.PARTIAL_MAX_ORDER`).
    """
    orders: list[int] = []
    for k, wanted in ((2, True), (3, residual_noise)):
        if wanted and 2 * k < steps and 3 + 2 * (len(orders) + 1) < steps:
            orders.append(k)
    return tuple(orders)


class DecodeError(ValueError):
    """Frames do not match the plan or cannot be decoded; the message says which and why."""


@dataclass(frozen=True)
class SetLayout:
    """One (axis, period) group: its phase shifts and how the sums are kept."""

    axis: str
    period_px: float
    amplitude: float
    steps: int
    psi: tuple[float, ...]  # phase shift of each step, radians


@dataclass
class SetSums:
    """The running sums of one (axis, period) group."""

    layout: SetLayout
    a: Any
    b: Any
    s0: Any
    excluded: Any | None = None  # per-pixel bit mask of clipped (excluded) steps
    harmonics: tuple[int, ...] = ()  # extra harmonic orders k modelled by the fit
    extra: list[Any] = field(default_factory=list)  # sum v sin(k psi), sum v cos(k psi) per k
    seen: int = 0

    @property
    def rows(self) -> int:
        """Number of sums kept: s0, a, b and two per extra harmonic."""
        return 3 + 2 * len(self.harmonics)


@dataclass
class KernelLayout:
    """The sets as the compiled kernels read them (accumulate_kernel.py, kernel_sums.py):
    each step's weight in each row of its set's sums, and where those rows are."""

    weights: np.ndarray  # (S, R, T) float32: weight of step t in row r of set s (row 0: s0)
    row0: np.ndarray  # (S,) int64 first row of each set in `FrameAccumulator.block`
    nrows: np.ndarray  # (S,) int64
    steps: np.ndarray  # (S,) int64


def _bits_dtype(steps: int) -> np.dtype:
    """Smallest unsigned integer dtype that holds one bit per phase step."""
    for dt in (np.uint8, np.uint16, np.uint32, np.uint64):
        if steps <= np.dtype(dt).itemsize * 8:
            return np.dtype(dt)
    raise DecodeError(f"plan: {steps} phase steps per period exceeds the supported 64")


class FrameAccumulator:
    """Accumulates frames tagged with plan indices; validates each against the plan."""

    def __init__(
        self,
        plan: Plan,
        shape: tuple[int, int],
        *,
        saturation_dn: float | None,
        saturation_margin: float = 0.0,
        need_squares: bool,
        xp: ModuleType = np,
    ) -> None:
        if len(shape) != 2 or min(shape) < 1:
            raise DecodeError(f"shape: expected (H, W) with H, W >= 1, got {shape}")
        self.plan = plan
        self.shape = (int(shape[0]), int(shape[1]))
        self.xp = xp
        self.saturation_dn = saturation_dn
        self.saturation_margin = saturation_margin
        self.need_squares = need_squares
        self.dtype: np.dtype | None = None
        self.high: float | None = None
        self.low: float | None = None
        # plan frames folded into the sums (a whole-stack decode marks them all at its start)
        self.added = np.zeros(len(plan.frames), dtype=bool)
        self.sets: list[SetSums] = []
        self.row0: list[int] = []  # first row of each set's sums (s0, a, b, extras) in `block`
        # plan index -> (kind, set, step) of each frame the decoder uses: kind "cos" (step of
        # set), "bright" or "dark"; other flats have no role
        self.roles: dict[int, tuple[str, int, int]] = {}
        for k, ps in enumerate(plan.period_sets()):
            frames = [plan.frames[i] for i in ps.frame_indices]
            amps = {f.amplitude for f in frames if isinstance(f, CosineFrame)}
            if len(amps) != 1:
                raise DecodeError(
                    f"plan: axis {ps.axis} period {ps.period_px:g} px mixes amplitudes "
                    f"{sorted(amps)}; the decoder needs one amplitude per period"
                )
            psi = tuple(2.0 * math.pi * s / ps.steps for s in range(ps.steps))
            layout = SetLayout(ps.axis, ps.period_px, amps.pop(), ps.steps, psi)
            sums = SetSums(layout, None, None, None)
            sums.harmonics = harmonic_orders(ps.steps, need_squares)
            self.row0.append(sum(s.rows for s in self.sets))
            self.sets.append(sums)
            for step, idx in enumerate(ps.frame_indices):
                self.roles[idx] = ("cos", k, step)
        self.rows = sum(s.rows for s in self.sets)
        self.bits_dtype = _bits_dtype(max(s.layout.steps for s in self.sets))
        levels = [f.level for f in plan.frames if isinstance(f, FlatFrame)]
        self.bright_level = max(levels)
        for i, f in enumerate(plan.frames):
            if isinstance(f, FlatFrame) and f.level == 0.0:
                self.roles[i] = ("dark", 0, 0)
            elif isinstance(f, FlatFrame) and f.level == self.bright_level:
                self.roles[i] = ("bright", 0, 0)
        self.compiled = False  # accumulate with the numba kernel (set by the decoder)
        self.block: Any | None = None  # (rows, H*W) float32 sums, allocated by `allocate`
        self.take: Any = None  # (shape, dtype) -> array to zero for the sums, None: new ones
        self.bits: Any | None = None  # (sets, H*W) bit masks of excluded steps, or None
        self.bright: Any | None = None
        self.dark: Any | None = None
        self.n_bright = 0
        self.n_dark = 0
        self.squares: Any | None = None
        self.squares_dtype = np.dtype(np.float64)
        self.max_seen = -math.inf  # brightest cosine sample seen (reported: saturation hint)

    @functools.cached_property
    def kernel_layout(self) -> KernelLayout:
        """Per-set weights of each step in each row (s0, a, b, extras): the weights
        `_add_cosine` applies, for the compiled kernels (built once)."""
        sets = self.sets
        weights = np.zeros((len(sets), max(s.rows for s in sets),
                            max(s.layout.steps for s in sets)), dtype=np.float32)
        for k, s in enumerate(sets):
            for t, psi in enumerate(s.layout.psi):
                row = [1.0, math.sin(psi), math.cos(psi)]
                for h in s.harmonics:
                    row += [math.sin(h * psi), math.cos(h * psi)]
                # the OpenCV path skips weights below 1e-12 (exact zeros of sin/cos)
                weights[k, :len(row), t] = [w if abs(w) > 1e-12 else 0.0 for w in row]
        return KernelLayout(weights, np.array(self.row0, dtype=np.int64),
                            np.array([s.rows for s in sets], dtype=np.int64),
                            np.array([s.layout.steps for s in sets], dtype=np.int64))

    def allocate(self) -> None:
        """Allocate and zero the full-image sums (once): the first `add` or a live capture's
        `prepare` pays the page faults, not the pose's last frame."""
        if self.block is not None:
            return
        h, w = self.shape
        self.block = self._zeros((self.rows, h * w), np.float32)
        for sums, r0 in zip(self.sets, self.row0, strict=True):
            rows = [self.block[r0 + r].reshape(self.shape) for r in range(sums.rows)]
            sums.s0, sums.a, sums.b, *sums.extra = rows
        self.bright = self._zeros(self.shape, np.float64)
        self.dark = self._zeros(self.shape, np.float64)
        if self.need_squares and self.dtype is not None:
            self.squares = self._zeros(self.shape, self.squares_dtype)
        if self.compiled:  # calloc'd: pages are touched only where a step clips
            self.bits = self.xp.zeros((len(self.sets), h * w), dtype=self.bits_dtype)

    def _zeros(self, shape: tuple[int, ...], dtype: Any) -> Any:
        """A zeroed array, written now so page faults happen here and not during capture
        (`take`, if set: e.g. an earlier decode's array, `sums_cache`)."""
        arr = self.xp.empty(shape, dtype=dtype) if self.take is None else self.take(shape, dtype)
        arr.fill(0)
        return arr

    @property
    def missing(self) -> list[int]:
        """Plan indices of frames the decoder needs that have not arrived."""
        return [i for i in sorted(self.roles) if not self.added[i]]

    def ready_frames(self, available: Any) -> list[int]:
        """Of the plan indices `available` (stored, not yet added), those worth adding now:
        flats and unused frames at once, cosine frames once every frame of their period
        group is available or already added (one cache-blocked pass per group, not one per
        frame); once one group is left, its frames as they come (one frame's pass after
        the last)."""
        have = set(int(i) for i in available)
        groups: dict[int, list[int]] = {}
        for index, (kind, k, _) in self.roles.items():
            if kind == "cos":
                groups.setdefault(k, []).append(index)
        ready = [i for i in sorted(have) if self.roles.get(i, ("flat",))[0] != "cos"]
        for members in groups.values():
            if all(i in have or self.added[i] for i in members):
                ready += [i for i in members if i in have]
        if ready:
            return sorted(ready)
        last = len({self.roles[i][:2] for i in self.missing}) == 1
        return sorted(int(i) for i in available) if last else []

    # -- intake ----------------------------------------------------------------------
    def check(self, index: int, image: Any) -> Any:
        """Validate one frame against the plan and the earlier frames; return it as an xp array
        (not marked added: the compiled paths check a whole batch before summing any)."""
        if isinstance(index, bool) or not isinstance(index, int | np.integer):
            raise DecodeError(f"frame index: expected an integer, got {index!r}")
        if not 0 <= index < len(self.plan.frames):
            raise DecodeError(
                f"frame {index}: index out of range (the plan has {len(self.plan.frames)} frames)"
            )
        if self.added[index]:
            raise DecodeError(f"frame {index}: already added (each plan frame exactly once)")
        if getattr(image, "ndim", None) != 2:
            shape = getattr(image, "shape", None)
            raise DecodeError(
                f"frame {index}: expected a single-channel 2-D image, got shape {shape}"
            )
        if tuple(image.shape) != self.shape:
            raise DecodeError(
                f"frame {index}: shape {tuple(image.shape)} differs from the camera "
                f"shape {self.shape}"
            )
        dt = np.dtype(image.dtype)
        if dt not in ACCEPTED_DTYPES:
            raise DecodeError(
                f"frame {index}: dtype {dt} not supported; expected uint8, uint16 or float32"
            )
        if self.dtype is None:
            self._set_dtype(dt)
        elif dt != self.dtype:
            raise DecodeError(
                f"frame {index}: dtype {dt} differs from the earlier frames' {self.dtype}"
            )
        return self.xp.asarray(image)

    def _set_dtype(self, dt: np.dtype) -> None:
        """Fix the frame dtype and the clipping levels it implies."""
        self.dtype = dt
        if dt.kind == "u":
            top = float(np.iinfo(dt).max)
            level = top if self.saturation_dn is None else float(self.saturation_dn)
            # Read noise added after the full well spreads saturated pixels just below it.
            self.high = level * (1.0 - self.saturation_margin)
            self.low = 0.0  # an integer 0 is a clipped reading, not a measurement
        else:
            self.high = (
                None
                if self.saturation_dn is None
                else float(self.saturation_dn) * (1.0 - self.saturation_margin)
            )
            self.low = None
        # uint8 squares summed in float32 stay exact integers (< 2**24 for <= 258 frames).
        small = dt == np.uint8 and len(self.plan.frames) <= 258
        self.squares_dtype = np.dtype(np.float32 if small else np.float64)
        if self.need_squares and self.block is not None:
            self.squares = self._zeros(self.shape, self.squares_dtype)

    def accept(self, index: int, image: Any) -> Any:
        """Validate plan frame `index`, allocate the sums, mark it seen; the frame as an xp
        array (for the compiled path, which sums it itself: calibration/decode/batch.py)."""
        img = self.check(index, image)
        self.allocate()
        self.added[index] = True
        return img

    def add(self, index: int, image: Any) -> None:
        """Fold one frame into the sums (any order, each plan index once)."""
        img = self.accept(index, image)
        role = self.roles.get(int(index))
        if role is None:
            return  # a flat at another level: not used by the decoder
        kind, k, step = role
        if kind == "bright":
            self._add_flat(self.bright, img)
            self.n_bright += 1
        elif kind == "dark":
            self._add_flat(self.dark, img)
            self.n_dark += 1
        else:
            self._add_cosine(k, step, img)

    def _add_flat(self, total: Any, img: Any) -> None:
        """Sum a flat frame (float64) for its per-pixel average."""
        if self.xp is np and cv2 is not None:
            cv2.accumulate(img, total)
        else:
            total += img

    def excluded_row(self, k: int) -> Any:
        """Set k's (H, W) bit mask of excluded steps, allocated on its first clipped sample."""
        sums = self.sets[k]
        if sums.excluded is None:
            if self.bits is None:
                h, w = self.shape
                self.bits = self.xp.zeros((len(self.sets), h * w), dtype=self.bits_dtype)
            sums.excluded = self.bits[k].reshape(self.shape)
        return sums.excluded

    def _exclude_clipped(self, k: int, step: int, img: Any) -> Any:
        """Zero the frame's clipped samples and record their step; fast when there are none."""
        if self.high is None and self.low is None:
            return img
        xp = self.xp
        fast = xp is np and cv2 is not None
        lo, hi = cv2.minMaxLoc(img)[:2] if fast else (float(img.min()), float(img.max()))
        self.max_seen = max(self.max_seen, float(hi))
        hit_hi = self.high is not None and hi >= self.high
        hit_lo = self.low is not None and lo <= self.low
        if not (hit_hi or hit_lo):
            return img
        excluded = self.excluded_row(k)
        bit = excluded.dtype.type(1 << step)
        if fast and img.dtype.kind == "u":
            # One fused range test and one masked copy (OpenCV SIMD) instead of 4 NumPy passes.
            top = np.iinfo(img.dtype).max
            lo_keep = int(self.low) + 1 if hit_lo else 0
            hi_keep = math.ceil(self.high) - 1 if hit_hi else top
            kept = cv2.inRange(img, lo_keep, hi_keep)
            np.bitwise_or(excluded, bit, out=excluded, where=kept == 0)
            return cv2.bitwise_and(img, img, mask=kept)
        clip = img >= self.high if hit_hi else None
        if hit_lo:
            clip = img <= self.low if clip is None else clip | (img <= self.low)
        excluded |= clip.astype(excluded.dtype) * bit
        return xp.where(clip, xp.zeros((), dtype=img.dtype), img)

    def _add_cosine(self, k: int, step: int, img: Any) -> None:
        """a += v sin(psi), b += v cos(psi), s0 += v, squares += v^2 over the kept samples."""
        sums = self.sets[k]
        img = self._exclude_clipped(k, step, img)
        psi = sums.layout.psi[step]
        pairs = [(sums.a, math.sin(psi)), (sums.b, math.cos(psi))]
        for j, k in enumerate(sums.harmonics):
            pairs.append((sums.extra[2 * j], math.sin(k * psi)))
            pairs.append((sums.extra[2 * j + 1], math.cos(k * psi)))
        pairs = [(acc, w) for acc, w in pairs if abs(w) > 1e-12]
        if self.xp is np and cv2 is not None:
            for acc, w in pairs:
                cv2.addWeighted(acc, 1.0, img, w, 0.0, dst=acc, dtype=cv2.CV_32F)
            cv2.accumulate(img, sums.s0)
            if self.squares is not None:
                cv2.accumulateSquare(img, self.squares)
        else:
            v = img.astype(self.xp.float32)
            for acc, w in pairs:
                acc += v * self.xp.float32(w)
            sums.s0 += v
            if self.squares is not None:
                self.squares += v.astype(self.squares.dtype) ** 2
        sums.seen += 1
