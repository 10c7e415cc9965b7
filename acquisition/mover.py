"""The `Mover` protocol: a robot arm or motorized stage that places the camera or the screen.

Beside `Display` and `Camera` (acquisition/protocols.py): a mover goes to a flange pose in
its base frame, reports the pose it reached (as its encoders see it), knows its workspace,
gives up after a timeout and stops at once when asked (from any thread). Backends: the
simulated arm and stages (hw_mocks/arm.py), a lab's own robot server over HTTP/JSON
(acquisition/movers/http.py); `acquisition/movers/conformance.py: check_mover` checks any
of them. Poses follow phasecal.robot-poses/1: `X_base = R @ X_flange + t`, millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from acquisition.errors import AcquisitionError


class MoverError(AcquisitionError):
    """The mover failed (lost link, drive fault); the message names the mover."""


class MoveRefused(MoverError):
    """The pose cannot be reached (outside the workspace, not on the stage's axes); the
    mover did not move."""


class MoveTimeout(MoverError):
    """The move did not finish within its timeout; the mover was stopped where it was."""


class MoveStopped(MoverError):
    """`stop()` ended the move before it finished; the mover stands where it stopped."""


@dataclass(frozen=True)
class RobotPose:
    """The flange's pose in the base frame: X_base = rotation @ X_flange + translation_mm."""

    rotation: np.ndarray
    translation_mm: np.ndarray

    def __post_init__(self) -> None:
        r = np.asarray(self.rotation, dtype=np.float64)
        t = np.asarray(self.translation_mm, dtype=np.float64)
        if r.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"pose: expected R 3x3 and t_mm [3], got {r.shape} and {t.shape}")
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
            raise ValueError("pose: R and t_mm must be finite")
        if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
            raise ValueError("pose: R is not a rotation matrix (orthonormal, det +1 to 1e-6)")
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation_mm", t)

    def to_json(self) -> dict[str, Any]:
        return {"R": self.rotation.tolist(), "t_mm": self.translation_mm.tolist()}

    @classmethod
    def from_json(cls, data: Any, where: str = "pose") -> RobotPose:
        """Parse {"R": 3x3, "t_mm": [3]}; ValueError naming `where` and the key."""
        if not isinstance(data, dict) or "R" not in data or "t_mm" not in data:
            raise ValueError(f"{where}: expected an object with keys R (3x3) and t_mm [3]")
        try:
            return cls(np.asarray(data["R"], dtype=np.float64),
                       np.asarray(data["t_mm"], dtype=np.float64))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}: {exc}") from None

    def __matmul__(self, other: RobotPose) -> RobotPose:
        """The composed transform: apply `other`, then this one."""
        return RobotPose(self.rotation @ other.rotation,
                         self.rotation @ other.translation_mm + self.translation_mm)

    def inverse(self) -> RobotPose:
        return RobotPose(self.rotation.T, -self.rotation.T @ self.translation_mm)

    def angle_to_deg(self, other: RobotPose) -> float:
        """Rotation angle between the two orientations, degrees."""
        c = (np.trace(self.rotation.T @ other.rotation) - 1.0) / 2.0
        return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))

    def distance_mm(self, other: RobotPose) -> float:
        return float(np.linalg.norm(self.translation_mm - other.translation_mm))


@dataclass(frozen=True)
class Workspace:
    """Where the flange may go: its origin inside a box (base frame, mm) and its orientation
    within `max_angle_deg` of `home_rotation`. Checked before any motion."""

    min_mm: tuple[float, float, float]
    max_mm: tuple[float, float, float]
    home_rotation: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0),
                                                    (0.0, 0.0, 1.0))
    max_angle_deg: float = 180.0

    def why_unreachable(self, pose: RobotPose) -> str | None:
        """None when `pose` is inside; else the reason, naming the axis or the angle."""
        t = pose.translation_mm
        for axis, value, lo, hi in zip("xyz", t, self.min_mm, self.max_mm, strict=True):
            if not lo <= value <= hi:
                return f"{axis} = {value:.3f} mm is outside the workspace [{lo:g}, {hi:g}] mm"
        home = RobotPose(np.asarray(self.home_rotation), np.zeros(3))
        angle = home.angle_to_deg(pose)
        if angle > self.max_angle_deg + 1e-9:
            return (f"orientation {angle:.2f} deg from home exceeds the workspace's "
                    f"{self.max_angle_deg:g} deg")
        return None

    def to_json(self) -> dict[str, Any]:
        return {"min_mm": list(self.min_mm), "max_mm": list(self.max_mm),
                "home_R": [list(r) for r in self.home_rotation],
                "max_angle_deg": self.max_angle_deg}

    @classmethod
    def from_json(cls, data: Any, where: str = "workspace") -> Workspace:
        """Parse `to_json`'s form; ValueError naming the key."""
        try:
            lo = tuple(float(v) for v in data["min_mm"])
            hi = tuple(float(v) for v in data["max_mm"])
            home = RobotPose(np.asarray(data.get("home_R", np.eye(3)), dtype=np.float64),
                             np.zeros(3)).rotation
            angle = float(data.get("max_angle_deg", 180.0))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: expected min_mm [3], max_mm [3], optional home_R 3x3 "
                             f"and max_angle_deg ({exc})") from None
        if len(lo) != 3 or len(hi) != 3 or any(a > b for a, b in zip(lo, hi, strict=True)):
            raise ValueError(f"{where}: min_mm and max_mm must be 3 values with min <= max")
        return cls(lo, hi, tuple(tuple(r) for r in home.tolist()), angle)  # type: ignore[arg-type]


@dataclass(frozen=True)
class MoverInfo:
    """Static facts about a mover. `axes` names what it can move ("x", "y", "z", "rx", "ry",
    "rz" for an arm; "pan", "tilt" or "travel" for stages); `repeatability_mm` /
    `repeatability_deg` are 1-sigma per-axis errors of a reached pose (what hand-eye weighs
    the robot's poses by; an ISO 9283 datasheet value is about three of these)."""

    name: str
    axes: tuple[str, ...]
    repeatability_mm: float
    repeatability_deg: float
    workspace: Workspace

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "axes": list(self.axes),
                "repeatability": {"mm": self.repeatability_mm, "deg": self.repeatability_deg},
                "workspace": self.workspace.to_json()}

    @classmethod
    def from_json(cls, data: Any, where: str = "info") -> MoverInfo:
        try:
            rep = data["repeatability"]
            return cls(str(data["name"]), tuple(str(a) for a in data["axes"]),
                       float(rep["mm"]), float(rep["deg"]),
                       Workspace.from_json(data["workspace"], f"{where}.workspace"))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"{where}: missing or malformed key {exc}") from None


@runtime_checkable
class Mover(Protocol):
    """A robot or stage that carries the camera or the screen on its flange.

    `move_to` blocks until the mover has settled at `pose` and returns the pose it reports
    having reached; it raises `MoveRefused` (nothing moved) for a pose it cannot reach,
    `MoveTimeout` after stopping the mover when `timeout_s` passes first, and `MoveStopped`
    when `stop()` (from another thread) ended it. `stop` halts any motion at once and is
    harmless when idle.
    """

    @property
    def info(self) -> MoverInfo: ...

    def move_to(self, pose: RobotPose, timeout_s: float) -> RobotPose: ...

    def current_pose(self) -> RobotPose: ...

    def stop(self) -> None: ...

    def close(self) -> None: ...
