"""A simulated robot arm and stages (the `Mover` protocol) and a hand-eye rig built on them.

The arm reaches a commanded pose with the errors a real one has: a random repeatability
error (1-sigma per axis, `repeatability_mm` / `repeatability_deg`) and backlash (the pose
lags behind along the direction it came from). Its encoders do not see either, so, like a
real robot, it reports the commanded pose; `true_pose()` is the simulator's truth. Moves
take real time (distance over speed plus a settling time) so that timeouts and `stop()`
from another thread behave as on hardware.

`HandEyeRig` mounts a camera on the flange looking at a fixed screen (eye-in-hand) or the
screen on the flange in front of a fixed camera (eye-to-hand), with known hand-eye and
world-target transforms (the truth tests and benchmarks compare hand-eye results with).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from acquisition.mover import (
    MoveRefused,
    MoverError,
    MoverInfo,
    MoveStopped,
    MoveTimeout,
    RobotPose,
    Workspace,
)
from acquisition.movers.stage import StageKinematics
from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import TruthCamera
from hw_mocks.poses import random_poses
from hw_mocks.scene import ScreenPose

Mount = Literal["eye-in-hand", "eye-to-hand"]


def _between(a: RobotPose, b: RobotPose, fraction: float) -> RobotPose:
    """The pose `fraction` of the way from a to b (rotation along the shortest arc)."""
    step = Rotation.from_matrix(b.rotation @ a.rotation.T).as_rotvec() * fraction
    rot = Rotation.from_rotvec(step).as_matrix() @ a.rotation
    return RobotPose(rot, a.translation_mm + fraction * (b.translation_mm - a.translation_mm))


class SimulatedMover:
    """Timed motion shared by the simulated arm and stages: `move_to` waits the move's
    duration (interruptible by `stop()`), then lands with repeatability and backlash errors."""

    def __init__(self, info: MoverInfo, start: RobotPose, *, backlash_mm: float = 0.0,
                 backlash_deg: float = 0.0, speed_mm_s: float = 250.0,
                 speed_deg_s: float = 60.0, settle_s: float = 0.05,
                 rng: np.random.Generator | None = None) -> None:
        self._info = info
        self._reported = start
        self._true = start
        self._backlash_mm = backlash_mm
        self._backlash_deg = backlash_deg
        self._speed_mm_s = speed_mm_s
        self._speed_deg_s = speed_deg_s
        self._settle_s = settle_s
        self._rng = rng or np.random.default_rng(0)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._closed = False
        self.moves = 0  # completed moves (tests and benchmarks count them)
        # called with the true flange pose after every move, finished or cut short (what a
        # simulated rig uses to carry the camera or the screen along)
        self.on_moved: list[Callable[[RobotPose], None]] = []

    @property
    def info(self) -> MoverInfo:
        return self._info

    def check_reachable(self, pose: RobotPose) -> None:
        """MoveRefused with the reason if `pose` is outside the workspace."""
        why = self._info.workspace.why_unreachable(pose)
        if why is not None:
            raise MoveRefused(f"{self._info.name}: {why}")

    def duration_s(self, pose: RobotPose) -> float:
        """How long a move from the current pose to `pose` takes, settling included."""
        travel = max(self._reported.distance_mm(pose) / self._speed_mm_s,
                     self._reported.angle_to_deg(pose) / self._speed_deg_s)
        return travel + self._settle_s

    def move_to(self, pose: RobotPose, timeout_s: float) -> RobotPose:
        if not timeout_s > 0:
            raise ValueError(f"timeout_s: expected > 0, got {timeout_s}")
        with self._lock:
            if self._closed:
                raise MoverError(f"{self._info.name}: closed")
            self.check_reachable(pose)
            start = self._reported
            duration = self.duration_s(pose)
            self._stop.clear()
            began = time.monotonic()
            stopped = self._stop.wait(min(duration, timeout_s))
            if stopped or duration > timeout_s:
                fraction = min(1.0, (time.monotonic() - began) / duration)
                self._arrive(_between(start, pose, fraction), None)
                if stopped:
                    raise MoveStopped(f"{self._info.name}: stopped {fraction:.0%} of the way")
                raise MoveTimeout(f"{self._info.name}: the move needs {duration:.3g} s, more "
                                  f"than its {timeout_s:.3g} s timeout; stopped "
                                  f"{fraction:.0%} of the way")
            self._arrive(pose, self._landed(start, pose))
            self.moves += 1
            return pose

    def _arrive(self, reported: RobotPose, true: RobotPose | None) -> None:
        """Stand at `reported` (really at `true`; None: exactly there) and tell `on_moved`."""
        self._reported = reported
        self._true = reported if true is None else true
        for listener in self.on_moved:
            listener(self._true)

    def _landed(self, start: RobotPose, pose: RobotPose) -> RobotPose:
        """Where the flange really ends up: backlash against the approach, then the random
        repeatability error (rotation in the base frame, position of the flange origin)."""
        rep_mm, rep_deg = self._info.repeatability_mm, self._info.repeatability_deg
        motion = pose.translation_mm - start.translation_mm
        lag = np.zeros(3)
        if np.linalg.norm(motion) > 0:
            lag = -self._backlash_mm * motion / np.linalg.norm(motion)
        turn = Rotation.from_matrix(pose.rotation @ start.rotation.T).as_rotvec()
        twist = np.zeros(3)
        if np.linalg.norm(turn) > 0:
            twist = -np.radians(self._backlash_deg) * turn / np.linalg.norm(turn)
        twist = twist + np.radians(rep_deg) * self._rng.standard_normal(3)
        rot = Rotation.from_rotvec(twist).as_matrix() @ pose.rotation
        return RobotPose(rot, pose.translation_mm + lag + rep_mm * self._rng.standard_normal(3))

    def current_pose(self) -> RobotPose:
        return self._reported

    def true_pose(self) -> RobotPose:
        """Where the flange really is (simulator truth; a robot cannot report it)."""
        return self._true

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self.stop()
        with self._lock:
            self._closed = True


class SimulatedArm(SimulatedMover):
    """A six-axis arm: any pose inside its workspace box and orientation cone."""

    def __init__(self, *, workspace: Workspace | None = None, repeatability_mm: float = 0.02,
                 repeatability_deg: float = 0.005, start: RobotPose | None = None,
                 name: str = "simulated arm", **motion: Any) -> None:
        ws = workspace or Workspace((-1500.0, -1500.0, -1500.0), (1500.0, 1500.0, 1500.0))
        info = MoverInfo(name, ("x", "y", "z", "rx", "ry", "rz"), repeatability_mm,
                         repeatability_deg, ws)
        super().__init__(info, start or RobotPose(np.eye(3), np.zeros(3)), **motion)


class SimulatedStage(SimulatedMover):
    """A pan-tilt head or linear rail (`StageKinematics`): poses off its axes are refused."""

    def __init__(self, kinematics: StageKinematics, *, repeatability_mm: float = 0.005,
                 repeatability_deg: float = 0.002, name: str | None = None,
                 **motion: Any) -> None:
        self.kinematics = kinematics
        home = kinematics.pose_for({axis: float(np.clip(0.0, *kinematics.limits[axis]))
                                    for axis in kinematics.axes})
        reach = 1e-3 + max(abs(v) for lim in kinematics.limits.values() for v in lim)
        lo = tuple(o - reach for o in kinematics.origin_mm)
        hi = tuple(o + reach for o in kinematics.origin_mm)
        info = MoverInfo(name or f"simulated {kinematics.kind} stage", kinematics.axes,
                         repeatability_mm, repeatability_deg,
                         Workspace(lo, hi))  # type: ignore[arg-type]
        super().__init__(info, home, **motion)

    def check_reachable(self, pose: RobotPose) -> None:
        super().check_reachable(pose)
        self.kinematics.values_for(pose)


@dataclass
class HandEyeRig:
    """A camera and a screen, one of them on a mover's flange, with the true transforms.

    eye-in-hand: `hand_eye` is the camera in the flange frame, `world_target` the screen in
    the base frame; eye-to-hand: `hand_eye` is the camera in the base frame, `world_target`
    the screen in the flange frame (phasecal.handeye/1's meaning)."""

    mount: Mount
    arm: SimulatedMover
    camera: TruthCamera
    screen: ScreenGeometry
    hand_eye: RobotPose
    world_target: RobotPose

    def screen_pose(self) -> ScreenPose:
        """Where the screen is in the camera frame at the arm's true pose."""
        return self.screen_pose_at(self.arm.true_pose())

    def screen_pose_at(self, flange: RobotPose) -> ScreenPose:
        """Where the screen is in the camera frame with the flange at `flange`."""
        if self.mount == "eye-in-hand":  # X_cam = (F X)^-1 Y S
            pose = (flange @ self.hand_eye).inverse() @ self.world_target
        else:  # X_cam = X^-1 F Y S
            pose = self.hand_eye.inverse() @ flange @ self.world_target
        return ScreenPose(pose.rotation, pose.translation_mm)

    def flange_pose_for(self, view: ScreenPose) -> RobotPose:
        """The flange pose that shows the screen at `view` (camera frame), errors aside."""
        a = RobotPose(view.rotation, view.translation)
        if self.mount == "eye-in-hand":  # F = Y A^-1 X^-1
            return self.world_target @ a.inverse() @ self.hand_eye.inverse()
        return self.hand_eye @ a @ self.world_target.inverse()  # F = X A Y^-1

    def view_plan(self, n: int, rng: np.random.Generator) -> list[RobotPose]:
        """`n` flange poses that show varied, well-covered views of the screen."""
        return [self.flange_pose_for(v) for v in random_poses(self.camera, self.screen, n, rng)]

    def truth(self) -> dict[str, Any]:
        return {"mount": self.mount, "hand_eye": self.hand_eye.to_json(),
                "world_target": self.world_target.to_json()}


def _rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    return Rotation.from_rotvec(np.radians(max_deg) * rng.uniform(-1, 1, 3) / np.sqrt(3)
                                ).as_matrix()


def handeye_rig(mount: Mount, camera: TruthCamera, screen: ScreenGeometry,
                rng: np.random.Generator, *, repeatability_mm: float = 0.02,
                repeatability_deg: float = 0.005, backlash_mm: float = 0.0,
                backlash_deg: float = 0.0, **motion: Any) -> HandEyeRig:
    """A plausible rig with random true transforms: a camera mounted ~100 mm off the flange
    and tilted a few degrees (eye-in-hand), or a screen mounted centred ~60 mm in front of
    the flange (eye-to-hand); the fixed part stands about a metre from the base."""
    arm = SimulatedArm(repeatability_mm=repeatability_mm, repeatability_deg=repeatability_deg,
                       backlash_mm=backlash_mm, backlash_deg=backlash_deg, rng=rng, **motion)
    fixed = RobotPose(Rotation.from_rotvec(rng.uniform(-1, 1, 3)).as_matrix(),
                      np.array([700.0, 0.0, 300.0]) + rng.uniform(-100, 100, 3))
    if mount == "eye-in-hand":
        hand_eye = RobotPose(_rotation(rng, 5.0), np.array([40.0, -25.0, 100.0])
                             + rng.uniform(-10, 10, 3))
        return HandEyeRig(mount, arm, camera, screen, hand_eye, fixed)
    center = np.array([(screen.width_px - 1) / 2 * screen.pitch_mm[0],
                       (screen.height_px - 1) / 2 * screen.pitch_mm[1], 0.0])
    rot = _rotation(rng, 5.0)
    on_flange = RobotPose(rot, np.array([0.0, 0.0, 60.0]) - rot @ center + rng.uniform(-5, 5, 3))
    return HandEyeRig(mount, arm, camera, screen, fixed, on_flange)
