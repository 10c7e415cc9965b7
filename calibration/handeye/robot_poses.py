"""The robot poses input, `phasecal.robot-poses/1`: the flange's pose in the base frame for
each view as the robot reported it, and the robot's stated repeatability."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from calibration.handeye.rigid import Rigid

ROBOT_POSES_FORMAT = "phasecal.robot-poses/1"


class RobotPosesError(ValueError):
    """The robot poses are malformed; the message names the key."""


@dataclass(frozen=True)
class RobotPoses:
    """Flange in base per view (X_base = R X_flange + t) and 1-sigma per-axis repeatability."""

    poses: dict[str, Rigid]
    repeatability_mm: float
    repeatability_deg: float

    def to_json(self) -> dict[str, Any]:
        return {"format": ROBOT_POSES_FORMAT,
                "poses": {v: p.to_json() for v, p in self.poses.items()},
                "repeatability": {"mm": self.repeatability_mm, "deg": self.repeatability_deg}}


def _rigid(data: Any, where: str) -> Rigid:
    if not isinstance(data, dict) or "R" not in data or "t_mm" not in data:
        raise RobotPosesError(f"{where}: expected an object with R (3x3) and t_mm [3]")
    try:
        r = np.asarray(data["R"], dtype=np.float64)
        t = np.asarray(data["t_mm"], dtype=np.float64)
    except (TypeError, ValueError):
        raise RobotPosesError(f"{where}: R and t_mm must be numbers") from None
    if r.shape != (3, 3) or t.shape != (3,):
        raise RobotPosesError(f"{where}: expected R 3x3 and t_mm [3], got shapes "
                              f"{r.shape} and {t.shape}")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
        raise RobotPosesError(f"{where}: non-finite values")
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
        raise RobotPosesError(f"{where}.R: not a rotation matrix (orthonormal with det +1, "
                              "to 1e-6)")
    return Rigid(r, t)


def robot_poses_from_dict(data: Any, source: str = "robot poses") -> RobotPoses:
    """Validate a parsed phasecal.robot-poses/1 document."""
    if not isinstance(data, dict) or data.get("format") != ROBOT_POSES_FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise RobotPosesError(f"{source}: format: expected {ROBOT_POSES_FORMAT!r}, got {got!r}")
    poses = data.get("poses")
    if not isinstance(poses, dict) or not poses:
        raise RobotPosesError(f"{source}: poses: expected an object VIEW -> {{R, t_mm}}")
    rep = data.get("repeatability")
    try:
        mm, deg = float(rep["mm"]), float(rep["deg"])  # type: ignore[index]
    except (TypeError, KeyError, ValueError):
        raise RobotPosesError(f"{source}: repeatability: expected {{\"mm\": number, \"deg\": "
                              "number}") from None
    if not (mm > 0 and deg > 0 and np.isfinite(mm) and np.isfinite(deg)):
        raise RobotPosesError(f"{source}: repeatability: mm and deg must be > 0 (the robot's "
                              f"1-sigma errors weigh its poses), got {mm}, {deg}")
    parsed = {str(v): _rigid(p, f"{source}: poses.{v}") for v, p in poses.items()}
    return RobotPoses(parsed, mm, deg)


def read_robot_poses(path: str | Path) -> RobotPoses:
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise RobotPosesError(f"{path}: not JSON ({exc})") from None
    return robot_poses_from_dict(data, str(path))
