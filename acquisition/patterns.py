"""Build pattern plans (presets and full control) and render plan frames to display codes.

The plan data model and its validation live in `calibration.shared.plan` (the decoder reads
plans too); this module chooses periods and turns linear-light frames into device codes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calibration.shared.plan import (
    CosineFrame,
    FlatFrame,
    Plan,
    PlanError,
    PlanFrame,
    cosine_frames,
    plan_from_dict,
)

__all__ = [
    "PRESETS",
    "DisplayResponse",
    "PlanPreset",
    "build_plan",
    "choose_periods",
    "frame_linear",
    "render_frame",
]


@dataclass(frozen=True)
class PlanPreset:
    """How to choose a plan: phase steps, finest period, largest period ratio."""

    steps: int
    finest_period_px: float
    max_ratio: float
    description: str


PRESETS: dict[str, PlanPreset] = {
    "default": PlanPreset(8, 24.0, 8.0, "8 steps, finest ~24 px, period ratio <= 8"),
    # 6 steps, not 4: N-step shifting aliases harmonics k = +-1 (mod N), and with 4 steps the
    # strong 3rd harmonic of an uncorrected gamma-2.2 display biased the phase (the demo's
    # residuals were 6x the noise floor); with 6 steps only the weak 5th and 7th alias.
    "fast": PlanPreset(6, 32.0, 6.0, "6 steps (fewer frames), finest ~32 px, ratio <= 6"),
    "precise": PlanPreset(12, 16.0, 6.0, "12 steps, finest ~16 px, ratio <= 6"),
    "blurry": PlanPreset(8, 64.0, 6.0, "8 steps, finest ~64 px for defocused cameras"),
}

# The coarsest period exceeds the screen extent by this factor so that the two screen
# edges never share a phase (the phase of that period is then unambiguous).
COARSEST_MARGIN = 1.05


def choose_periods(extent_px: int, finest_period_px: float, max_ratio: float) -> list[float]:
    """Geometric period ladder from >= extent down to ~finest, each ratio <= max_ratio.

    docs/physics.md section 3: the coarsest period covers the screen (no ambiguity) and each
    ratio is small enough that the coarser period's sigma is a small fraction of the
    finer period, so the Bayesian unwrapping picks the right order reliably.
    """
    if extent_px <= 0:
        raise PlanError(f"screen extent must be > 0 px, got {extent_px}")
    if finest_period_px <= 0:
        raise PlanError(f"finest period must be > 0 px, got {finest_period_px}")
    if max_ratio <= 1.0:
        raise PlanError(f"max period ratio must be > 1, got {max_ratio}")
    coarsest = float(math.ceil(extent_px * COARSEST_MARGIN))
    if finest_period_px >= coarsest:
        return [coarsest]
    total = coarsest / finest_period_px
    n = max(1, math.ceil(math.log(total) / math.log(max_ratio) - 1e-9))
    ratio = total ** (1.0 / n)
    return [round(coarsest / ratio**k, 3) for k in range(n + 1)]


def build_plan(
    width_px: int,
    height_px: int,
    pitch_mm: float | Sequence[float],
    *,
    preset: str = "default",
    axes: Sequence[str] = ("x", "y"),
    steps: int | None = None,
    periods_x: Sequence[float] | None = None,
    periods_y: Sequence[float] | None = None,
    finest_period_px: float | None = None,
    max_ratio: float | None = None,
    offset: float = 0.5,
    amplitude: float = 0.5,
) -> Plan:
    """Build and validate a plan: white and dark flats, then each axis' periods x steps.

    A preset provides defaults; any explicit argument overrides it (full control).
    """
    if preset not in PRESETS:
        raise PlanError(f"preset: unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    p = PRESETS[preset]
    steps = p.steps if steps is None else steps
    finest = p.finest_period_px if finest_period_px is None else finest_period_px
    ratio = p.max_ratio if max_ratio is None else max_ratio
    pitch = [float(pitch_mm)] * 2 if isinstance(pitch_mm, int | float) else list(pitch_mm)
    for axis in axes:
        if axis not in ("x", "y"):
            raise PlanError(f"axes: unknown axis {axis!r}; expected 'x' or 'y'")
    frames: list[dict] = [{"kind": "flat", "level": 1.0}, {"kind": "flat", "level": 0.0}]
    for axis in axes:
        extent = width_px if axis == "x" else height_px
        explicit = periods_x if axis == "x" else periods_y
        periods = list(explicit) if explicit else choose_periods(extent, finest, ratio)
        periods = sorted((float(t) for t in periods), reverse=True)
        for f in cosine_frames(axis, periods, steps):  # type: ignore[arg-type]
            frames.append(
                {
                    "kind": "cosine",
                    "axis": f.axis,
                    "period_px": f.period_px,
                    "step": f.step,
                    "steps": f.steps,
                    "offset": offset,
                    "amplitude": amplitude,
                }
            )
    data = {
        "format": "phasecal.plan/1",
        "screen": {"width_px": width_px, "height_px": height_px, "pitch_mm": pitch},
        "frames": frames,
    }
    return plan_from_dict(data, source="plan")


# -- rendering ---------------------------------------------------------------------


@dataclass(frozen=True)
class DisplayResponse:
    """Measured display response: linear light (0..1) produced by each device code.

    `levels` are increasing device codes (not necessarily all of them), `linear` the
    normalized light measured at each. Used to pre-compensate gamma (the LUT).
    """

    levels: np.ndarray
    linear: np.ndarray

    def __post_init__(self) -> None:
        lv = np.asarray(self.levels, dtype=np.float64)
        li = np.asarray(self.linear, dtype=np.float64)
        if lv.ndim != 1 or lv.shape != li.shape or lv.size < 2:
            raise ValueError("display response: levels and linear must be 1-D, same length >= 2")
        if np.any(np.diff(lv) <= 0):
            raise ValueError("display response: levels must be strictly increasing")
        if np.any(np.diff(li) < 0):
            raise ValueError("display response: linear light must not decrease with level")
        object.__setattr__(self, "levels", lv)
        object.__setattr__(self, "linear", li)

    @classmethod
    def gamma(cls, gamma: float, bit_depth: int = 8) -> DisplayResponse:
        """An ideal power-law response (for tests and as a default guess)."""
        top = (1 << bit_depth) - 1
        levels = np.arange(top + 1, dtype=np.float64)
        return cls(levels, (levels / top) ** gamma)

    def code_for(self, linear: np.ndarray) -> np.ndarray:
        """Continuous device code that produces the given linear light (inverse response)."""
        lo, hi = self.linear[0], self.linear[-1]
        target = lo + np.clip(linear, 0.0, 1.0) * (hi - lo)
        # np.interp needs strictly increasing x: nudge flat stretches apart.
        x = self.linear + np.arange(self.linear.size) * 1e-12
        return np.interp(target, x, self.levels)


def frame_linear(plan: Plan, index: int, dtype=np.float64) -> np.ndarray:
    """Linear-light image (height_px, width_px) in [0, 1] of plan frame `index`."""
    if not 0 <= index < len(plan.frames):
        raise PlanError(f"frame index {index} out of range (plan has {len(plan.frames)} frames)")
    frame: PlanFrame = plan.frames[index]
    h, w = plan.screen.height_px, plan.screen.width_px
    if isinstance(frame, FlatFrame):
        return np.full((h, w), frame.level, dtype=dtype)
    assert isinstance(frame, CosineFrame)
    n = w if frame.axis == "x" else h
    c = np.arange(n, dtype=np.float64)
    line = frame.offset + frame.amplitude * np.cos(
        2.0 * np.pi * c / frame.period_px + frame.phase_shift
    )
    line = np.clip(line, 0.0, 1.0).astype(dtype)
    return np.broadcast_to(line[None, :] if frame.axis == "x" else line[:, None], (h, w)).copy()


def _bayer_matrix(n: int) -> np.ndarray:
    """Ordered-dither threshold matrix of size n x n (n a power of two), values in (0, 1)."""
    m = np.zeros((1, 1))
    while m.shape[0] < n:
        m = np.block([[4 * m, 4 * m + 2], [4 * m + 3, 4 * m + 1]])
    return (m + 0.5) / m.size


def render_frame(
    plan: Plan,
    index: int,
    *,
    bit_depth: int = 8,
    response: DisplayResponse | None = None,
    dither: str | None = "ordered",
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Device codes (uint8 for 8 bit, uint16 for 10 bit) showing plan frame `index`.

    `response` pre-compensates the display's non-linearity (codes chosen so the emitted
    light is the plan's linear value). `dither` ('ordered', 'random' or None) spreads
    the rounding error so its local mean is zero: quantization then adds noise instead
    of a systematic, pattern-locked phase error.
    """
    if bit_depth not in (8, 10):
        raise ValueError(f"bit_depth: expected 8 or 10, got {bit_depth}")
    top = (1 << bit_depth) - 1
    linear = frame_linear(plan, index)
    code = response.code_for(linear) if response is not None else linear * top
    if dither == "ordered":
        h, w = code.shape
        # The tile is shifted per frame so that the small residual error of ordered
        # dithering on sloped patterns differs between phase steps and averages out.
        tile = np.roll(_bayer_matrix(8), (index * 3 % 8, index * 5 % 8), axis=(0, 1))
        thresh = np.tile(tile, (h // 8 + 1, w // 8 + 1))[:h, :w]
        out = np.floor(code + thresh)
    elif dither == "random":
        gen = rng if rng is not None else np.random.default_rng(index)
        out = np.floor(code + gen.random(code.shape))
    elif dither is None:
        out = np.rint(code)
    else:
        raise ValueError(f"dither: expected 'ordered', 'random' or None, got {dither!r}")
    out = np.clip(out, 0, top)
    return out.astype(np.uint8 if bit_depth == 8 else np.uint16)

