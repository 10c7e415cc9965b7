"""A whole simulated rig: display + optics + sensor + camera on one clock, with ground truth.

Built from a few settings (or a `phasecal.rig/1` config dict). The screen pose can be
changed between poses (`set_pose`); ambient light, gain drift and panel brightness can
be changed at any time, also mid-sequence via `at_frame`, to test integrity checks.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from acquisition.clock import Clock, RealClock
from acquisition.errors import DeviceSettingsError
from acquisition.protocols import CameraSettings
from acquisition.rig import Rig, RigConfig
from calibration.shared.plan import ScreenGeometry
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


class SimulatedRig:
    """Simulated display and camera sharing a clock; the screen pose is settable."""

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
    ) -> None:
        self.clock: Clock = clock if clock is not None else VirtualClock()
        self.truth_camera = truth_camera
        self.screen = screen
        if pose is None:
            pose = look_at_pose(screen, distance_mm=fill_distance_mm(truth_camera, screen, 0.9))
        self.display = SimulatedDisplay(screen.width_px, screen.height_px, self.clock,
                                        **(display or {}))
        self._optics_params = {"supersample": 1, **(optics or {})}
        setup = OpticalSetup(truth_camera, pose, screen, **self._optics_params)
        self.sensor = SensorModel(**(sensor or {}))
        self.camera = SimulatedCamera(self.display, setup, self.sensor, self.clock,
                                      faults=faults, **(camera or {}))
        default_format = "Mono8" if self.sensor.bit_depth == 8 else "Mono12"
        self.camera_settings = settings or CameraSettings(
            exposure_s=0.02, pixel_format=default_format, trigger_mode="software")
        # what the controller takes: these devices, with this simulator's controls
        self.rig = Rig(self.display, self.camera, self.clock, self.camera_settings, screen,
                       simulated=self)

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
        cam = {k: v for k, v in (config.get("camera") or {}).items() if k != "backend"}
        _reject_unknown("display", disp, _DISPLAY_KEYS)
        model = cam.pop("model", "mild_pinhole")
        w, h = int(cam.pop("width", 160)), int(cam.pop("height", 120))
        optics = {k: cam.pop(k) for k in list(cam) if k in _OPTICS_KEYS}
        if config.get("panel"):  # a shaped panel behind cover glass (PanelShape fields)
            optics["panel"] = PanelShape(**config["panel"])
        sensor = {k: cam.pop(k) for k in list(cam) if k in _SENSOR_KEYS}
        _reject_unknown("camera", cam, _CAMERA_KEYS)
        if "trigger_modes" in cam:
            cam["trigger_modes"] = tuple(cam["trigger_modes"])
        if clock is None:
            clock = RealClock() if config.get("clock") == "real" else VirtualClock()
        st = config.get("settings")
        settings = CameraSettings(**{**st, "extra": dict(st.get("extra") or {})}) if st else None
        return cls(make_truth_camera(model, w, h), screen, clock=clock, display=disp,
                   optics=optics, sensor=sensor, camera=cam, settings=settings)

    # -- ground truth and changes between/within poses ---------------------------------
    @property
    def optics(self) -> OpticalSetup:
        """The optical setup the camera renders with now."""
        return self.camera.optics

    @property
    def pose(self) -> ScreenPose:
        """Where the screen is now."""
        return self.camera.optics.pose

    def set_pose(self, rotation: np.ndarray, translation_mm: np.ndarray) -> None:
        """Move the screen: X_cam = R S + t (takes effect for the next rendered frame)."""
        pose = ScreenPose(np.asarray(rotation, np.float64), np.asarray(translation_mm, np.float64))
        old = self.camera.optics
        self.camera.optics = OpticalSetup(self.truth_camera, pose, self.screen,
                                          **{**self._optics_params, "ambient": old.ambient})

    def set_ambient(self, electrons_per_s: float) -> None:
        """Change constant stray light (flicker/room light injection)."""
        self.camera.optics.ambient = float(electrons_per_s)
        self._optics_params["ambient"] = float(electrons_per_s)

    def set_gain_drift(self, drift_db: float) -> None:
        """Add `drift_db` to the camera's gain (auto-gain/auto-exposure drift injection)."""
        self.camera.gain_drift_db = float(drift_db)

    def at_frame(self, n: int, action: Callable[[], None]) -> None:
        """Run `action` before the n-th frame delivered from now on is rendered."""
        self.camera.at_frame(n, action)

    def truth(self) -> dict[str, Any]:
        """Optical ground truth of the current pose (screen point per pixel, visibility, ...)."""
        return self.camera.optics.truth()

    def with_settings(self, **changes: Any) -> CameraSettings:
        """The rig's default camera settings with some fields changed."""
        return replace(self.camera_settings, **changes)


def _reject_unknown(part: str, params: dict[str, Any], allowed: set[str]) -> None:
    """One clear error for a misspelled simulated-device parameter."""
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise DeviceSettingsError(f"simulated {part}: unknown parameter(s) {unknown}; "
                                  f"allowed: {sorted(allowed)}")


def open_simulated_rig(config: RigConfig, clock: Clock | None = None) -> Rig:
    """The `acquisition.rig.SimulatorFactory` of this package: a `Rig` around a `SimulatedRig`
    built from a `kind = "simulated"` config."""
    sim = SimulatedRig.from_config(config.model_dump(mode="json", exclude_none=True),
                                   clock=clock)
    sim.rig.config = config
    if config.settings:
        sim.rig.settings = config.settings.to_settings()
    return sim.rig
