"""A whole simulated rig: display + optics + sensor + camera on one clock, with ground truth.

Built from a few settings (or a `phasecal.rig/1` config dict), with one camera or several
(`cameras`: each its own lens, resolution, timing and place, `CameraMount`). The screen pose can be
changed between poses (`set_pose`); ambient light, gain drift and panel brightness can
be changed at any time, also mid-sequence via `at_frame`, to test integrity checks. A
config's simulated mover (`mover = {backend = "simulated-arm" | ...}`) comes with the rig
as `Rig.mover` (`hw_mocks.arm`) and carries the camera (eye-in-hand: the screen stands in the
base frame) or the screen (eye-to-hand: the camera stands in the base frame): after each
move the screen pose follows from its true flange pose (`carry_on_mover`), so a closed loop
runs on the simulator as on a robot. The hand-eye and world-target transforms are fixed
(`SimulatedRig.handeye`, the truth) and put the screen where the rig starts it at the
mover's home pose.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from acquisition.clock import Clock, RealClock
from acquisition.errors import DeviceSettingsError
from acquisition.mover import RobotPose, Workspace
from acquisition.mover_config import (
    SimulatedArmConfig,
    SimulatedLinearConfig,
    SimulatedPanTiltConfig,
)
from acquisition.movers.stage import StageKinematics
from acquisition.protocols import CameraSettings
from acquisition.rig import DEFAULT_CAMERA, Rig, RigConfig
from calibration.shared.plan import ScreenGeometry
from hw_mocks.arm import HandEyeRig, Mount, SimulatedArm, SimulatedMover, SimulatedStage
from hw_mocks.camera import CameraFaults, SimulatedCamera
from hw_mocks.cameras import TruthCamera, make_truth_camera
from hw_mocks.clock import VirtualClock
from hw_mocks.display import SimulatedDisplay
from hw_mocks.optics import OpticalSetup
from hw_mocks.panel import PanelShape
from hw_mocks.poses import fill_distance_mm, look_at_pose
from hw_mocks.scene import ScreenPose
from hw_mocks.sensor import SensorModel

DEFAULT_SCREEN = ScreenGeometry(640, 400, (0.25, 0.25))
_DISPLAY_KEYS = {"refresh_hz", "latency_periods", "gamma", "bit_depth", "vsync_phase_s"}
_OPTICS_KEYS = {"blur_sigma_screen_px", "vignetting", "irradiance_scale", "ambient", "supersample"}
_SENSOR_KEYS = {"bit_depth", "full_well_e", "read_noise_e", "black_level_dn"}
_CAMERA_KEYS = {"trigger_modes", "default_frame_rate_hz", "max_frame_rate_hz", "buffer_depth",
                "timestamp_jitter_s", "trigger_latency_s", "readout_s", "seed", "replay"}
_FAULT_KEYS = {"lost_triggers"}  # triggers (1-based) whose frame arrives incomplete
_MOUNT_KEYS = {"extrinsics"}  # several cameras: {rvec, t_mm}, reference frame -> this camera's
BASELINE_FRACTION = 0.15  # default spacing of a rig's cameras, times the screen distance
DEFAULT_MOUNT: Mount = "eye-in-hand"  # what a simulated mover carries: the camera
# eye-in-hand: the camera ~110 mm off the flange, tilted a few degrees, as a bracket holds it
CAMERA_ON_FLANGE = RobotPose(Rotation.from_rotvec(np.radians([2.0, -3.0, 1.5])).as_matrix(),
                             np.array([40.0, -25.0, 100.0]))
SCREEN_STANDOFF_MM = 60.0  # eye-to-hand: the screen's centre this far in front of the flange


@dataclass
class CameraMount:
    """One simulated camera of a rig and where it sits: X_cam = R @ X_ref + t (mm), the
    reference camera's frame mapped into this camera's (the reference has identity)."""

    name: str
    truth_camera: TruthCamera
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    optics: dict[str, Any] = field(default_factory=dict)
    sensor: dict[str, Any] = field(default_factory=dict)
    camera: dict[str, Any] = field(default_factory=dict)  # SimulatedCamera keyword arguments
    settings: CameraSettings | None = None  # None: the rig's (or the sensor's default)
    faults: CameraFaults | None = None

    def screen_pose(self, reference_pose: ScreenPose) -> ScreenPose:
        """The screen seen from this camera, given where it is in the reference frame."""
        return ScreenPose(self.rotation @ reference_pose.rotation,
                          self.rotation @ reference_pose.translation + self.translation_mm)


def looking_at(centre_mm: np.ndarray, target_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a camera at `centre_mm` of the reference frame looking at `target_mm`, its
    x axis kept level (perpendicular to the reference y axis)."""
    z = np.asarray(target_mm, float) - np.asarray(centre_mm, float)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(z, x), z])
    return rot, -rot @ np.asarray(centre_mm, float)


def default_mount_centre(k: int, distance_mm: float) -> np.ndarray:
    """Where the k-th additional camera (k >= 1) sits by default: right, left, below,
    above the reference, then further out, `BASELINE_FRACTION` of the screen distance apart."""
    step = BASELINE_FRACTION * distance_mm * (1 + (k - 1) // 4)
    axis, sign = [(0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)][(k - 1) % 4]
    centre = np.zeros(3)
    centre[axis] = sign * step
    return centre


class SimulatedRig:
    """Simulated display and cameras sharing a clock; the screen pose is settable.

    The first camera is the reference: screen poses are given in its frame, and each other
    camera (`others`) sees the screen through its `CameraMount`."""

    def __init__(
        self,
        truth_camera: TruthCamera,
        screen: ScreenGeometry = DEFAULT_SCREEN,
        *,
        clock: Clock | None = None,
        pose: ScreenPose | None = None,
        display: dict[str, Any] | None = None,
        optics: dict[str, Any] | None = None,
        sensor: dict[str, Any] | None = None,
        camera: dict[str, Any] | None = None,
        settings: CameraSettings | None = None,
        faults: CameraFaults | None = None,
        name: str = DEFAULT_CAMERA,
        others: Sequence[CameraMount] = (),
    ) -> None:
        self.clock: Clock = clock if clock is not None else VirtualClock()
        self.truth_camera = truth_camera
        self.screen = screen
        if pose is None:
            pose = look_at_pose(screen, distance_mm=fill_distance_mm(truth_camera, screen, 0.9))
        self.display = SimulatedDisplay(screen.width_px, screen.height_px, self.clock,
                                        **(display or {}))
        self.mounts = {name: CameraMount(name, truth_camera, optics=optics or {},
                                         sensor=sensor or {}, camera=camera or {},
                                         settings=settings, faults=faults)}
        for mount in others:
            if mount.name in self.mounts:
                raise ValueError(f"cameras: duplicate camera name {mount.name!r}")
            self.mounts[mount.name] = mount
        self.cameras: dict[str, SimulatedCamera] = {}
        all_settings: dict[str, CameraSettings] = {}
        for k, mount in enumerate(self.mounts.values()):
            setup = OpticalSetup(mount.truth_camera, mount.screen_pose(pose), screen,
                                 **{"supersample": 1, **mount.optics})
            sensor_model = SensorModel(**mount.sensor)
            params = {"name": f"simulated camera {mount.name}", "serial": f"SIM{k + 1:04d}",
                      **({"seed": k} if k else {}), **mount.camera}
            self.cameras[mount.name] = SimulatedCamera(self.display, setup, sensor_model,
                                                       self.clock, faults=mount.faults,
                                                       **params)
            default_format = "Mono8" if sensor_model.bit_depth == 8 else "Mono12"
            all_settings[mount.name] = mount.settings or settings or CameraSettings(
                exposure_s=0.02, pixel_format=default_format, trigger_mode="software")
        self.camera = self.cameras[name]
        self.sensor = self.camera.base_sensor
        self.camera_settings = all_settings[name]
        # what the controller takes: these devices, with this simulator's controls
        self.rig = Rig(self.display, self.camera, self.clock, self.camera_settings, screen,
                       simulated=self, cameras=dict(self.cameras),
                       camera_settings={n: st for n, st in all_settings.items() if n != name})
        self.handeye: HandEyeRig | None = None  # set by `carry_on_mover`: the mover's truth

    @classmethod
    def from_config(cls, config: dict[str, Any], clock: Clock | None = None) -> SimulatedRig:
        """Build from a `phasecal.rig/1` dict (simulated parts); unknown keys are errors."""
        scr = config.get("screen") or {}
        width = scr.get("width_px") or DEFAULT_SCREEN.width_px
        height = scr.get("height_px") or DEFAULT_SCREEN.height_px
        pitch = scr.get("pitch_mm") or DEFAULT_SCREEN.pitch_mm
        pitch = (float(pitch), float(pitch)) if np.isscalar(pitch) else tuple(map(float, pitch))
        screen = ScreenGeometry(int(width), int(height), pitch)
        disp = {k: v for k, v in (config.get("display") or {}).items() if k != "backend"}
        _reject_unknown("display", disp, _DISPLAY_KEYS)
        if clock is None:
            clock = RealClock() if config.get("clock") == "real" else VirtualClock()
        st = config.get("settings")
        settings = _settings(st) if st else None
        entries = config.get("cameras") or [{**(config.get("camera") or {}),
                                             "name": DEFAULT_CAMERA}]
        panel = PanelShape(**config["panel"]) if config.get("panel") else None
        mounts = [_mount(entry, panel) for entry in entries]
        first = mounts[0]
        pose = look_at_pose(screen, distance_mm=fill_distance_mm(first.truth_camera, screen, 0.9))
        distance = float(np.linalg.norm(pose.translation + pose.rotation @ _screen_centre(screen)))
        target = np.array([0.0, 0.0, distance])
        for k, (mount, entry) in enumerate(zip(mounts[1:], entries[1:], strict=True), start=1):
            if "extrinsics" not in entry:
                mount.rotation, mount.translation_mm = looking_at(
                    default_mount_centre(k, distance), target)
        return cls(first.truth_camera, screen, clock=clock, pose=pose, display=disp,
                   optics=first.optics, sensor=first.sensor, camera=first.camera,
                   settings=first.settings or settings, faults=first.faults, name=first.name,
                   others=[replace(m, settings=m.settings or settings) for m in mounts[1:]])

    # -- ground truth and changes between/within poses ---------------------------------
    @property
    def optics(self) -> OpticalSetup:
        """The optical setup the reference camera renders with now."""
        return self.camera.optics

    @property
    def pose(self) -> ScreenPose:
        """Where the screen is now (in the reference camera's frame)."""
        return self.camera.optics.pose

    def truth_camera_of(self, name: str) -> TruthCamera:
        """A camera's true model, by name."""
        return self.mounts[name].truth_camera

    def set_pose(self, rotation: np.ndarray, translation_mm: np.ndarray) -> None:
        """Move the screen: X_ref = R S + t (takes effect for the next rendered frame)."""
        pose = ScreenPose(np.asarray(rotation, np.float64), np.asarray(translation_mm, np.float64))
        for name, cam in self.cameras.items():
            mount = self.mounts[name]
            cam.optics = OpticalSetup(mount.truth_camera, mount.screen_pose(pose), self.screen,
                                      **{"supersample": 1, **mount.optics,
                                         "ambient": cam.optics.ambient})

    def set_ambient(self, electrons_per_s: float) -> None:
        """Change constant stray light (flicker/room light injection), seen by every camera."""
        for name, cam in self.cameras.items():
            cam.optics.ambient = float(electrons_per_s)
            self.mounts[name].optics["ambient"] = float(electrons_per_s)

    def set_gain_drift(self, drift_db: float) -> None:
        """Add `drift_db` to every camera's gain (auto-gain/auto-exposure drift injection)."""
        for cam in self.cameras.values():
            cam.gain_drift_db = float(drift_db)

    def at_frame(self, n: int, action: Callable[[], None]) -> None:
        """Run `action` before the reference camera's n-th frame delivered from now on."""
        self.camera.at_frame(n, action)

    def drop_frame(self, camera: str, n: int) -> None:
        """The n-th trigger of `camera` from now on (1-based) delivers an incomplete frame, as
        a lost packet on a GigE link does (`FrameLost`)."""
        cam = self.cameras[camera]
        cam.faults.lost_triggers = cam.faults.lost_triggers | {cam.triggers_fired + n}

    def carry_on_mover(self, mover: SimulatedMover, mount: Mount = DEFAULT_MOUNT) -> HandEyeRig:
        """Put the reference camera (eye-in-hand) or the screen (eye-to-hand) on `mover`'s
        flange so the screen pose follows every move; the fixed transforms are chosen so that
        the screen stands where it is now at the mover's present pose. Returns the truth."""
        home = mover.true_pose()
        view = RobotPose(self.pose.rotation, self.pose.translation)
        if mount == "eye-in-hand":  # view = (F X)^-1 Y  ->  Y = F X view
            hand_eye = CAMERA_ON_FLANGE
            world_target = home @ hand_eye @ view
        else:  # view = X^-1 F Y  ->  X = F Y view^-1, the screen centred before the flange
            world_target = RobotPose(np.eye(3), np.array([0.0, 0.0, SCREEN_STANDOFF_MM])
                                     - _screen_centre(self.screen))
            hand_eye = home @ world_target @ view.inverse()
        self.handeye = HandEyeRig(mount, mover, self.truth_camera, self.screen, hand_eye,
                                  world_target)
        mover.on_moved.append(self._follow_mover)
        return self.handeye

    def _follow_mover(self, flange: RobotPose) -> None:
        """Place the screen where the camera sees it with the mover's flange at `flange`."""
        assert self.handeye is not None
        seen = self.handeye.screen_pose_at(flange)
        self.set_pose(seen.rotation, seen.translation)

    def truth(self, camera: str | None = None) -> dict[str, Any]:
        """Optical ground truth of the current pose (screen point per pixel, visibility, ...)
        for one camera (default: the reference)."""
        return self.cameras[camera or self.rig.reference].optics.truth()

    def with_settings(self, **changes: Any) -> CameraSettings:
        """The rig's default camera settings with some fields changed."""
        return replace(self.camera_settings, **changes)


def _screen_centre(screen: ScreenGeometry) -> np.ndarray:
    """The screen's centre in its own frame (mm)."""
    return np.array([(screen.width_px - 1) / 2 * screen.pitch_mm[0],
                     (screen.height_px - 1) / 2 * screen.pitch_mm[1], 0.0])


def _settings(data: dict[str, Any]) -> CameraSettings:
    """Camera settings from a config section."""
    return CameraSettings(**{**data, "extra": dict(data.get("extra") or {})})


def _mount(entry: dict[str, Any], panel: PanelShape | None) -> CameraMount:
    """One simulated camera of a config (`camera` or an entry of `cameras`)."""
    cam = {k: v for k, v in entry.items() if k not in ("backend", "name", "settings")}
    label = "camera" if entry.get("name") == DEFAULT_CAMERA else f"camera {entry.get('name')!r}"
    model = cam.pop("model", "mild_pinhole")
    w, h = int(cam.pop("width", 160)), int(cam.pop("height", 120))
    optics = {k: cam.pop(k) for k in list(cam) if k in _OPTICS_KEYS}
    if panel is not None:  # a shaped panel behind cover glass (PanelShape fields)
        optics["panel"] = panel
    sensor = {k: cam.pop(k) for k in list(cam) if k in _SENSOR_KEYS}
    lost = cam.pop("lost_triggers", None)
    extrinsics = cam.pop("extrinsics", None)
    _reject_unknown(label, cam, _CAMERA_KEYS | _FAULT_KEYS | _MOUNT_KEYS)
    if "trigger_modes" in cam:
        cam["trigger_modes"] = tuple(cam["trigger_modes"])
    mount = CameraMount(str(entry.get("name") or DEFAULT_CAMERA),
                        make_truth_camera(model, w, h), optics=optics, sensor=sensor,
                        camera=cam, settings=_settings(entry["settings"])
                        if entry.get("settings") else None,
                        faults=CameraFaults(lost_triggers=frozenset(int(n) for n in lost))
                        if lost else None)
    if extrinsics is not None:
        rvec = np.asarray(extrinsics.get("rvec", (0.0, 0.0, 0.0)), np.float64).reshape(3, 1)
        mount.rotation = cv2.Rodrigues(rvec)[0]
        mount.translation_mm = np.asarray(extrinsics.get("t_mm", (0.0, 0.0, 0.0)),
                                          np.float64).reshape(3)
    return mount


def _reject_unknown(part: str, params: dict[str, Any], allowed: set[str]) -> None:
    """One clear error for a misspelled simulated-device parameter."""
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise DeviceSettingsError(f"simulated {part}: unknown parameter(s) {unknown}; "
                                  f"allowed: {sorted(allowed)}")


def simulated_mover(cfg: SimulatedArmConfig | SimulatedPanTiltConfig | SimulatedLinearConfig
                    ) -> SimulatedMover:
    """The simulated arm or stage a rig config's `mover` section describes."""
    motion = {"speed_mm_s": cfg.speed_mm_s, "speed_deg_s": cfg.speed_deg_s,
              "settle_s": cfg.settle_s, "backlash_mm": cfg.backlash_mm,
              "backlash_deg": cfg.backlash_deg, "rng": np.random.default_rng(cfg.seed),
              **{k: v for k in ("repeatability_mm", "repeatability_deg")
                 if (v := getattr(cfg, k)) is not None}}
    if isinstance(cfg, SimulatedArmConfig):
        ws = cfg.workspace
        workspace = None if ws is None else Workspace(ws.min_mm, ws.max_mm,
                                                      max_angle_deg=ws.max_angle_deg)
        return SimulatedArm(workspace=workspace, **motion)
    if isinstance(cfg, SimulatedPanTiltConfig):
        kinematics = StageKinematics("pan-tilt", cfg.origin_mm,
                                     {"pan": cfg.pan_deg, "tilt": cfg.tilt_deg})
    else:
        kinematics = StageKinematics("linear", cfg.origin_mm, {"travel": cfg.travel_mm},
                                     direction=cfg.direction)
    return SimulatedStage(kinematics, **motion)


def open_simulated_rig(config: RigConfig, clock: Clock | None = None) -> Rig:
    """The `acquisition.rig.SimulatorFactory` of this package: a `Rig` around a `SimulatedRig`
    built from a `kind = "simulated"` config, with its simulated mover if it names one (a
    robot server, `http`, is connected by `acquisition.rig.open_rig`)."""
    sim = SimulatedRig.from_config(config.model_dump(mode="json", exclude_none=True),
                                   clock=clock)
    sim.rig.config = config
    if config.settings:
        sim.rig.settings = config.settings.to_settings()
    if isinstance(config.mover, SimulatedArmConfig | SimulatedPanTiltConfig
                  | SimulatedLinearConfig):
        mover = simulated_mover(config.mover)
        sim.carry_on_mover(mover, config.mover.mount)
        sim.rig.mover = mover
    return sim.rig
