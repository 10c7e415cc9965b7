"""Kinematics of stages with fewer axes than an arm: a pan-tilt head and a linear rail.

A stage goes through the same `Mover` protocol as an arm, so it takes full flange poses;
these say which poses lie on its axes (and refuse the rest with the reason) and convert
between a pose and the axis values a stage driver is commanded in.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from acquisition.mover import MoveRefused, RobotPose

StageKind = Literal["pan-tilt", "linear"]

# A pose off the stage's axes by more than this is refused (rounding in a client's JSON and
# its matrix products stays far below it).
_ON_AXES_MM = 1e-6
_ON_AXES_RAD = 1e-6


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


@dataclass(frozen=True)
class StageKinematics:
    """`pan-tilt`: R = Rz(pan) @ Rx(tilt) about the fixed point `origin_mm` (axes "pan",
    "tilt", degrees); `linear`: identity orientation, t = origin_mm + travel * direction
    (axis "travel", mm). `limits` gives each axis' (low, high)."""

    kind: StageKind
    origin_mm: tuple[float, float, float]
    limits: dict[str, tuple[float, float]]
    direction: tuple[float, float, float] = (1.0, 0.0, 0.0)

    @property
    def axes(self) -> tuple[str, ...]:
        return ("pan", "tilt") if self.kind == "pan-tilt" else ("travel",)

    def pose_for(self, values: dict[str, float]) -> RobotPose:
        """The flange pose at these axis values (no limit check)."""
        origin = np.asarray(self.origin_mm, dtype=np.float64)
        if self.kind == "pan-tilt":
            rot = _rz(np.radians(values["pan"])) @ _rx(np.radians(values["tilt"]))
            return RobotPose(rot, origin)
        d = np.asarray(self.direction, dtype=np.float64)
        return RobotPose(np.eye(3), origin + values["travel"] * d / np.linalg.norm(d))

    def values_for(self, pose: RobotPose) -> dict[str, float]:
        """The axis values that reach `pose`; MoveRefused if no values do (off the stage's
        axes or beyond a limit), naming what is wrong."""
        origin = np.asarray(self.origin_mm, dtype=np.float64)
        if self.kind == "pan-tilt":
            rot = pose.rotation
            pan = np.arctan2(rot[1, 0], rot[0, 0])
            m = _rz(-pan) @ rot
            values = {"pan": float(np.degrees(pan)),
                      "tilt": float(np.degrees(np.arctan2(m[2, 1], m[1, 1])))}
            off = pose.distance_mm(RobotPose(np.eye(3), origin))
            if off > _ON_AXES_MM:
                raise MoveRefused(f"pan-tilt stage: the pose is {off:.4g} mm from the stage's "
                                  "fixed point; a pan-tilt head only rotates")
        else:
            d = np.asarray(self.direction, dtype=np.float64)
            d = d / np.linalg.norm(d)
            values = {"travel": float((pose.translation_mm - origin) @ d)}
            if pose.angle_to_deg(RobotPose(np.eye(3), origin)) > np.degrees(_ON_AXES_RAD):
                raise MoveRefused("linear stage: the pose is rotated; a linear stage only "
                                  "translates")
        reached = self.pose_for(values)
        if (reached.distance_mm(pose) > _ON_AXES_MM
                or np.radians(reached.angle_to_deg(pose)) > _ON_AXES_RAD):
            raise MoveRefused(f"{self.kind} stage: the pose is not on the stage's axes "
                              f"({', '.join(self.axes)}); nearest axis values {values}")
        for axis, value in values.items():
            lo, hi = self.limits[axis]
            if not lo <= value <= hi:
                raise MoveRefused(f"{self.kind} stage: {axis} = {value:.4g} is outside its "
                                  f"limits [{lo:g}, {hi:g}]")
        return values
