"""Pattern plans (`phasecal.plan/1`): the data model, validation and JSON I/O.

The plan lives here, in the lowest layer, because both the acquisition side (which
builds and shows plans, `acquisition.patterns`) and the decoder read it.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from calibration.shared.atomic import write_json_atomic

PLAN_FORMAT = "phasecal.plan/1"

Axis = Literal["x", "y"]


class PlanError(ValueError):
    """A plan is malformed; the message names the file, the field and what was expected."""


@dataclass(frozen=True)
class ScreenGeometry:
    """Screen size in pixels and pixel pitch in millimetres."""

    width_px: int
    height_px: int
    pitch_mm: tuple[float, float]

    def extent_px(self, axis: Axis) -> int:
        """Number of screen pixels along an axis."""
        return self.width_px if axis == "x" else self.height_px


@dataclass(frozen=True)
class FlatFrame:
    """A uniform frame of linear-light `level` in [0, 1]."""

    level: float
    kind: Literal["flat"] = "flat"


@dataclass(frozen=True)
class CosineFrame:
    """`offset + amplitude * cos(2*pi*c/period_px + 2*pi*step/steps)` along `axis`."""

    axis: Axis
    period_px: float
    step: int
    steps: int
    offset: float = 0.5
    amplitude: float = 0.5
    kind: Literal["cosine"] = "cosine"

    @property
    def phase_shift(self) -> float:
        """The frame's phase shift psi in radians."""
        return 2.0 * math.pi * self.step / self.steps


PlanFrame = FlatFrame | CosineFrame


@dataclass(frozen=True)
class PeriodSet:
    """All frames of one (axis, period): their plan indices ordered by step."""

    axis: Axis
    period_px: float
    steps: int
    frame_indices: tuple[int, ...]


@dataclass(frozen=True)
class Plan:
    """A validated pattern plan: screen geometry and the ordered list of frames."""

    screen: ScreenGeometry
    frames: tuple[PlanFrame, ...]
    extra: tuple[tuple[str, Any], ...] = ()

    # -- views used by the decoder and the controller -------------------------------
    def period_sets(self, axis: Axis | None = None) -> list[PeriodSet]:
        """Group cosine frames by (axis, period), coarsest period first."""
        groups: dict[tuple[str, float, int], list[tuple[int, int]]] = {}
        for i, f in enumerate(self.frames):
            if isinstance(f, CosineFrame) and (axis is None or f.axis == axis):
                groups.setdefault((f.axis, f.period_px, f.steps), []).append((f.step, i))
        out = [
            PeriodSet(ax, period, steps, tuple(i for _, i in sorted(members)))
            for (ax, period, steps), members in groups.items()
        ]
        return sorted(out, key=lambda s: (s.axis, -s.period_px))

    def axes(self) -> list[Axis]:
        """Axes that have cosine frames, in x, y order."""
        present = {f.axis for f in self.frames if isinstance(f, CosineFrame)}
        return [a for a in ("x", "y") if a in present]

    def flat_indices(self, level: float) -> list[int]:
        """Indices of flat frames with the given level."""
        return [
            i for i, f in enumerate(self.frames) if isinstance(f, FlatFrame) and f.level == level
        ]

    def to_dict(self) -> dict[str, Any]:
        """The plan as `phasecal.plan/1` JSON data."""
        frames: list[dict[str, Any]] = []
        for f in self.frames:
            if isinstance(f, FlatFrame):
                frames.append({"kind": "flat", "level": f.level})
            else:
                frames.append(
                    {
                        "kind": "cosine",
                        "axis": f.axis,
                        "period_px": f.period_px,
                        "step": f.step,
                        "steps": f.steps,
                        "offset": f.offset,
                        "amplitude": f.amplitude,
                    }
                )
        data: dict[str, Any] = {"format": PLAN_FORMAT}
        data.update(dict(self.extra))
        data["screen"] = {
            "width_px": self.screen.width_px,
            "height_px": self.screen.height_px,
            "pitch_mm": list(self.screen.pitch_mm),
        }
        data["frames"] = frames
        return data

    def digest(self) -> str:
        """A stable short hash of the plan content (recorded in decoded maps)."""
        blob = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":")).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


# -- validation --------------------------------------------------------------------


def _number(value: Any, where: str, *, positive: bool = False, lo=None, hi=None) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise PlanError(f"{where}: expected a finite number, got {value!r}")
    v = float(value)
    if positive and v <= 0:
        raise PlanError(f"{where}: must be > 0, got {value!r}")
    if lo is not None and v < lo:
        raise PlanError(f"{where}: must be >= {lo}, got {value!r}")
    if hi is not None and v > hi:
        raise PlanError(f"{where}: must be <= {hi}, got {value!r}")
    return v


def _integer(value: Any, where: str, *, lo: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise PlanError(f"{where}: expected an integer, got {value!r}")
    if lo is not None and value < lo:
        raise PlanError(f"{where}: must be >= {lo}, got {value!r}")
    return value


def _parse_frame(raw: Any, where: str) -> PlanFrame:
    if not isinstance(raw, dict):
        raise PlanError(f"{where}: expected an object, got {type(raw).__name__}")
    kind = raw.get("kind")
    if kind == "flat":
        if "level" not in raw:
            raise PlanError(f"{where}.level: missing (flat frames need a level in [0, 1])")
        return FlatFrame(level=_number(raw["level"], f"{where}.level", lo=0.0, hi=1.0))
    if kind == "cosine":
        for key in ("axis", "period_px", "step", "steps"):
            if key not in raw:
                raise PlanError(f"{where}.{key}: missing (cosine frames need {key})")
        axis = raw["axis"]
        if axis not in ("x", "y"):
            raise PlanError(f"{where}.axis: unknown axis {axis!r}; expected 'x' or 'y'")
        period = _number(raw["period_px"], f"{where}.period_px", positive=True)
        steps = _integer(raw["steps"], f"{where}.steps")
        if steps < 3:
            raise PlanError(f"{where}.steps: need at least 3 phase steps, got {steps}")
        step = _integer(raw["step"], f"{where}.step", lo=0)
        if step >= steps:
            raise PlanError(f"{where}.step: must be < steps ({steps}), got {step}")
        offset = _number(raw.get("offset", 0.5), f"{where}.offset", lo=0.0, hi=1.0)
        amplitude = _number(raw.get("amplitude", 0.5), f"{where}.amplitude", positive=True)
        if offset - amplitude < -1e-9 or offset + amplitude > 1 + 1e-9:
            raise PlanError(
                f"{where}: offset ± amplitude must stay within [0, 1], got "
                f"offset={offset}, amplitude={amplitude}"
            )
        return CosineFrame(axis, period, step, steps, offset, amplitude)
    raise PlanError(f"{where}.kind: unknown frame kind {kind!r}; expected 'flat' or 'cosine'")


def _check_complete(plan: Plan, source: str) -> None:
    """Every (axis, period) must have all its steps exactly once; flats must exist."""
    seen: dict[tuple[str, float, int], list[int]] = {}
    for f in plan.frames:
        if isinstance(f, CosineFrame):
            seen.setdefault((f.axis, f.period_px, f.steps), []).append(f.step)
    if not seen:
        raise PlanError(f"{source}: frames: the plan has no cosine frames")
    for (axis, period, steps), got in seen.items():
        if sorted(got) != list(range(steps)):
            raise PlanError(
                f"{source}: frames: axis {axis} period {period:g} px needs steps "
                f"0..{steps - 1} exactly once each, got {sorted(got)}"
            )
    for axis in plan.axes():
        extent = plan.screen.extent_px(axis)
        coarsest = max(p for (a, p, _) in seen if a == axis)
        if coarsest < extent:
            raise PlanError(
                f"{source}: frames: the coarsest {axis} period ({coarsest:g} px) must cover "
                f"the screen extent ({extent} px) so the phase is unambiguous"
            )
    if not plan.flat_indices(1.0) and not any(
        isinstance(f, FlatFrame) and f.level > 0.5 for f in plan.frames
    ):
        raise PlanError(f"{source}: frames: a bright flat frame (level 1.0) is required")
    if not plan.flat_indices(0.0):
        raise PlanError(f"{source}: frames: a dark flat frame (level 0.0) is required")


def plan_from_dict(data: Any, source: str = "plan") -> Plan:
    """Validate `phasecal.plan/1` data and build a `Plan` (raises `PlanError`)."""
    if not isinstance(data, dict):
        raise PlanError(f"{source}: expected a JSON object, got {type(data).__name__}")
    fmt = data.get("format")
    if fmt != PLAN_FORMAT:
        raise PlanError(f"{source}: format: expected {PLAN_FORMAT!r}, got {fmt!r}")
    screen_raw = data.get("screen")
    if not isinstance(screen_raw, dict):
        raise PlanError(f"{source}: screen: missing (need width_px, height_px, pitch_mm)")
    for key in ("width_px", "height_px", "pitch_mm"):
        if key not in screen_raw:
            raise PlanError(f"{source}: screen.{key}: missing")
    width = _integer(screen_raw["width_px"], f"{source}: screen.width_px", lo=1)
    height = _integer(screen_raw["height_px"], f"{source}: screen.height_px", lo=1)
    pitch_raw = screen_raw["pitch_mm"]
    if isinstance(pitch_raw, int | float) and not isinstance(pitch_raw, bool):
        pitch_raw = [pitch_raw, pitch_raw]
    if not isinstance(pitch_raw, list | tuple) or len(pitch_raw) != 2:
        raise PlanError(f"{source}: screen.pitch_mm: expected [pitch_x, pitch_y] in mm")
    pitch = (
        _number(pitch_raw[0], f"{source}: screen.pitch_mm[0]", positive=True),
        _number(pitch_raw[1], f"{source}: screen.pitch_mm[1]", positive=True),
    )
    frames_raw = data.get("frames")
    if not isinstance(frames_raw, list) or not frames_raw:
        raise PlanError(f"{source}: frames: expected a non-empty list of frames")
    frames = tuple(_parse_frame(f, f"{source}: frames[{i}]") for i, f in enumerate(frames_raw))
    extra = tuple(
        (k, v) for k, v in data.items() if k not in ("format", "screen", "frames")
    )
    plan = Plan(ScreenGeometry(width, height, pitch), frames, extra)
    _check_complete(plan, source)
    return plan


def read_plan(path: str | Path) -> Plan:
    """Read and validate a plan JSON file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise PlanError(f"{p}: plan file not found") from None
    except OSError as exc:
        raise PlanError(f"{p}: cannot read plan: {exc.strerror}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise PlanError(f"{p}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    return plan_from_dict(data, source=str(p))


def write_plan(plan: Plan, path: str | Path) -> None:
    """Write a plan as JSON (atomically: temp file then rename)."""
    write_json_atomic(path, plan.to_dict(), indent=2)


def cosine_frames(axis: Axis, periods: Iterable[float], steps: int) -> list[CosineFrame]:
    """All phase steps for each period of one axis, period-major order."""
    return [CosineFrame(axis, float(T), s, steps) for T in periods for s in range(steps)]
