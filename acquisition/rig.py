"""Rig configuration (TOML or JSON -> `RigConfig`) and opening a rig's devices.

A rig is one display, one camera or several named ones (`cameras = [{name = "left", ...}]`,
any mix of backends, captured in sync on the one screen), the screen geometry (pixel pitch in
mm), the camera settings to start from, optionally a USB trigger box and a mover (a robot
arm or stage that places the camera or the screen: `mover = {backend = ...}`).
`kind = "hardware"` opens real backends; `kind = "simulated"` (the default) is opened by
the `SimulatorFactory` the caller passes (`hw_mocks.rig.open_simulated_rig`, wired in by
`api`), simulated movers included, so real code never imports the simulator.
See docs/hardware.md and docs/rigs/*.toml for examples.
"""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PositiveFloat,
    ValidationError,
    model_validator,
)

from acquisition.clock import Clock, RealClock
from acquisition.errors import AcquisitionError
from acquisition.mover import Mover, RobotPose
from acquisition.mover_config import (
    SIMULATED_MOVERS,
    HttpMoverConfig,
    MoverBase,
    MoverConfig,
    open_mover,
)
from acquisition.patterns import DisplayResponse
from acquisition.protocols import Camera, CameraSettings, Display, SimulatorControls
from acquisition.usb.trigger_box import TriggerSink
from calibration.shared.plan import ScreenGeometry

RIG_FORMAT = "phasecal.rig/1"
DEFAULT_CAMERA = "cam0"  # the name of a one-camera rig's camera (`camera = {...}`)
CAMERA_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$")  # also a folder name


class RigConfigError(ValueError):
    """A rig config file is invalid; the message names the file and the field."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ScreenConfig(_Strict):
    """The screen's pixel pitch (mm) and, optionally, its size (default: the display's)."""

    pitch_mm: PositiveFloat | tuple[PositiveFloat, PositiveFloat] | None = None
    width_px: int | None = Field(default=None, gt=0)
    height_px: int | None = Field(default=None, gt=0)


class PanelConfig(_Strict):
    """Simulated rigs: the emitting layer's bow/twist (mm) behind a cover glass (thickness mm,
    index), traced exactly by `hw_mocks.panel.PanelShape` (docs/physics.md section 8)."""

    bow_x_mm: float = Field(default=0.0, allow_inf_nan=False,
                            description="sag centre to x edges (+: towards the camera)")
    bow_y_mm: float = Field(default=0.0, allow_inf_nan=False, description="the same along y")
    twist_mm: float = Field(default=0.0, allow_inf_nan=False, description="xi * eta term")
    glass_mm: float = Field(default=0.0, ge=0, allow_inf_nan=False,
                            description="cover glass thickness (0: a bare panel)")
    glass_index: float = Field(default=1.52, ge=1.0, le=3.0, description="its refractive index")

    @model_validator(mode="after")
    def _behind_glass(self) -> PanelConfig:
        """The shaped panel must stay behind the glass's front surface."""
        sag = (abs(self.bow_x_mm) + abs(self.bow_y_mm)) / 3 + abs(self.twist_mm)
        if self.glass_mm > 0 and sag >= self.glass_mm:
            raise ValueError(f"the panel reaches {sag:.3g} mm in front of its mean plane, "
                             f"through the {self.glass_mm} mm glass: thicker glass or less bow")
        return self


class FramebufferConfig(_Strict):
    """Linux framebuffer display; geometry from the device, a sysfs folder, or given here."""

    backend: Literal["framebuffer"]
    device: str = "/dev/fb0"
    sysfs_root: str | None = None
    width: int | None = Field(default=None, gt=0)
    height: int | None = Field(default=None, gt=0)
    bits_per_pixel: Literal[16, 24, 32] | None = None
    line_length: int | None = Field(default=None, gt=0)
    refresh_hz: float | None = Field(default=None, gt=0)


class SdlConfig(_Strict):
    """Full-screen SDL (pygame) window on a monitor."""

    backend: Literal["sdl"]
    monitor: int = Field(default=0, ge=0)
    width: int | None = Field(default=None, gt=0)
    height: int | None = Field(default=None, gt=0)
    refresh_hz: float = Field(default=60.0, gt=0)
    vsync: bool = True
    video_driver: str | None = None


class SimulatedPart(BaseModel):
    """Simulated display or camera: its parameters go to `hw_mocks` unchanged."""

    model_config = ConfigDict(extra="allow")
    backend: Literal["simulated"] = "simulated"


class OpenCvConfig(_Strict):
    """OpenCV VideoCapture camera: device index, /dev/videoN, or a recording."""

    backend: Literal["opencv"]
    source: int | str = 0
    width: int | None = Field(default=None, gt=0)
    height: int | None = Field(default=None, gt=0)
    buffers: int = Field(default=2, ge=1)
    replay_rate_hz: float | None = Field(default=None, gt=0)
    v4l2_controls: bool = True


class AravisConfig(_Strict):
    """GenICam camera through Aravis, opened by id or address (never by discovery)."""

    backend: Literal["aravis"]
    device: str = Field(min_length=1)
    buffers: int = Field(default=8, ge=2)
    bayer: Literal["demosaic", "raw"] = "demosaic"
    trigger_line: str = "Line0"
    region: tuple[int, int, int, int] | None = None  # x, y, width, height on the sensor


DisplayConfig = Annotated[FramebufferConfig | SdlConfig | SimulatedPart,
                          Field(discriminator="backend")]
CameraConfig = Annotated[OpenCvConfig | AravisConfig | SimulatedPart,
                         Field(discriminator="backend")]
AnyCamera = OpenCvConfig | AravisConfig | SimulatedPart


class SettingsConfig(_Strict):
    """Camera settings to start from (`phasecal check` and auto-setup may refine them)."""

    exposure_s: float = Field(default=0.010, gt=0)
    gain_db: float = 0.0
    pixel_format: str = "Mono8"
    trigger_mode: Literal["software", "hardware", "free-running"] = "free-running"
    frame_rate_hz: float | None = Field(default=None, gt=0)
    extra: dict[str, float | int | str] = Field(default_factory=dict)

    def to_settings(self) -> CameraSettings:
        """As the protocol's `CameraSettings`."""
        return CameraSettings(self.exposure_s, self.gain_db, self.pixel_format,
                              self.trigger_mode, self.frame_rate_hz, dict(self.extra))


class NamedCamera(BaseModel):
    """What a camera of a several-camera rig has besides its backend: its name (a folder
    and query name) and, optionally, its own settings (default: the rig's)."""

    name: str = Field(pattern=CAMERA_NAME_RE.pattern,
                      description="letters, digits, '_' and '-', at most 32")
    settings: SettingsConfig | None = None


class NamedOpenCvCamera(OpenCvConfig, NamedCamera):
    """An OpenCV camera of a several-camera rig."""


class NamedAravisCamera(AravisConfig, NamedCamera):
    """An Aravis camera of a several-camera rig."""


class NamedSimulatedCamera(SimulatedPart, NamedCamera):
    """A simulated camera of a several-camera rig (`extrinsics` places it, see hw_mocks)."""


NamedCameraConfig = Annotated[NamedOpenCvCamera | NamedAravisCamera | NamedSimulatedCamera,
                              Field(discriminator="backend")]


class TriggerBoxConfig(_Strict):
    """A USB trigger box fired on each display flip (vendor control transfer)."""

    vendor_id: int = Field(ge=0, le=0xFFFF)
    product_id: int = Field(ge=0, le=0xFFFF)
    serial: str | None = None
    request: int = Field(default=1, ge=0, le=0xFF)
    index: int = Field(default=0, ge=0, le=0xFFFF)


class RigConfig(_Strict):
    """A whole rig: `phasecal.rig/1`."""

    format: Literal["phasecal.rig/1"] = RIG_FORMAT
    kind: Literal["simulated", "hardware"] = "simulated"
    name: str | None = None
    # Simulated rigs run on virtual time by default ("real": wall-clock pacing, e.g. for
    # watching a demo); hardware rigs always use the real clock.
    clock: Literal["virtual", "real"] | None = None
    screen: ScreenConfig = Field(default_factory=ScreenConfig)
    display: DisplayConfig = Field(default_factory=SimulatedPart)
    camera: CameraConfig | None = None  # one camera (the default: a simulated one) ...
    cameras: list[NamedCameraConfig] | None = Field(default=None, min_length=1, max_length=16)
    settings: SettingsConfig | None = None
    trigger_box: TriggerBoxConfig | None = None
    panel: PanelConfig | None = None  # simulated rigs: a shaped panel behind cover glass
    mover: MoverConfig | None = None  # a robot arm or stage that places camera or screen

    @model_validator(mode="before")
    @classmethod
    def _default_backends(cls, data: Any) -> Any:
        """Simulated rigs may omit `backend`; hardware rigs must name theirs."""
        if not isinstance(data, dict):
            return data
        data = dict(data)
        if data.get("camera") is None and data.get("cameras") is None:
            data["camera"] = {"backend": "simulated"}  # one camera, simulated by default
        if data.get("kind", "simulated") == "simulated":
            def simulated(part: Any) -> Any:
                return {**part, "backend": "simulated"} \
                    if isinstance(part, dict) and "backend" not in part else part
            for part in ("display", "camera"):
                if part in data:
                    data[part] = simulated(data[part])
            if isinstance(data.get("cameras"), list):
                data["cameras"] = [simulated(c) for c in data["cameras"]]
        return data

    def camera_entries(self) -> list[tuple[str, AnyCamera, SettingsConfig | None]]:
        """(name, config, own settings or None) of every camera, the reference first; a
        one-camera rig's camera is named `DEFAULT_CAMERA`."""
        if self.cameras is None:
            assert self.camera is not None
            return [(DEFAULT_CAMERA, self.camera, None)]
        return [(c.name, c, c.settings) for c in self.cameras]

    @model_validator(mode="after")
    def _consistent(self) -> RigConfig:
        if self.camera is not None and self.cameras is not None:
            raise ValueError("give camera (one camera) or cameras (several), not both")
        names = [name for name, _, _ in self.camera_entries()]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"cameras: duplicate camera name(s) {twice}; each camera needs "
                             "its own name")
        parts = [("display", self.display)] + [
            (f"camera {name!r}" if self.cameras is not None else "camera", cfg)
            for name, cfg, _ in self.camera_entries()]
        sim = [p for p, cfg in parts if cfg.backend == "simulated"]
        if self.kind == "hardware" and sim:
            raise ValueError(f"kind 'hardware' needs real backends; {sim} simulated")
        if self.kind == "simulated" and len(sim) != len(parts):
            raise ValueError("kind 'simulated' uses the simulated display and cameras; set "
                             "kind = 'hardware' to use real backends")
        if self.kind == "hardware" and self.panel is not None:
            raise ValueError("panel describes a simulated screen; a real monitor's shape and "
                             "glass are estimated by the fit (calibrate with options screen: "
                             "\"fit\")")
        if (self.kind == "hardware" and self.mover is not None
                and self.mover.backend in SIMULATED_MOVERS):
            raise ValueError(f"mover: backend {self.mover.backend!r} is for simulated rigs; "
                             "a hardware rig reaches its robot through its server (backend "
                             "'http')")
        if self.kind == "hardware" and self.clock == "virtual":
            raise ValueError("clock 'virtual' is only for simulated rigs (hardware runs in "
                             "real time)")
        if self.kind == "hardware" and self.screen.pitch_mm is None:
            raise ValueError("screen.pitch_mm is missing: the monitor's pixel pitch in mm "
                             "(panel width in mm / width in px), required for real displays")
        return self


def parse_rig_config(data: dict[str, Any], source: str = "rig config") -> RigConfig:
    """Validate rig config data; RigConfigError names the source and the field."""
    try:
        return RigConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err.get("loc", ())) or "(top level)"
        raise RigConfigError(f"{source}: {where}: {err.get('msg')}") from None


def load_rig_config(path: str | Path) -> RigConfig:
    """Read a TOML (`.toml`) or JSON rig config file."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FileNotFoundError(f"rig config {path}: no such file") from None
    try:
        data = tomllib.loads(text) if path.suffix != ".json" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise RigConfigError(f"rig config {path}: not valid {path.suffix[1:].upper()}: "
                             f"{exc}") from None
    return parse_rig_config(data, f"rig config {path}")


@dataclass
class Rig:
    """An opened rig, the only thing the acquisition controller takes: devices on one clock,
    the screen, the camera settings to use, and what was measured on it once (flip-to-panel
    latency, display response) so later poses reuse it.

    `camera` and `settings` are the reference camera's (a one-camera rig's only camera);
    `cameras` holds every camera by name, the reference first, and `camera_settings` the
    settings of the others (`settings_for`). `mover` is the robot or stage that places the
    camera or the screen, if the rig has one; `move_to` gives each move `move_timeout_s`."""

    display: Display
    camera: Camera
    clock: Clock
    settings: CameraSettings
    screen: ScreenGeometry
    config: RigConfig | None = None  # None for a rig assembled in code
    trigger: TriggerSink | None = None  # fired after each flip in 'hardware' trigger mode
    simulated: SimulatorControls | None = None  # simulator-only controls; None on real rigs
    display_response: DisplayResponse | None = None  # gamma LUT (`measure_display_response`)
    latency_s: float | None = None  # flip-to-panel latency, measured on first capture
    cameras: dict[str, Camera] = field(default_factory=dict)  # {} -> {DEFAULT_CAMERA: camera}
    camera_settings: dict[str, CameraSettings] = field(default_factory=dict)
    mover: Mover | None = None
    move_timeout_s: float = MoverBase.model_fields["timeout_s"].default
    _closed: bool = field(default=False, repr=False)

    def __post_init__(self) -> None:
        """A rig assembled with one camera names it `DEFAULT_CAMERA`."""
        if not self.cameras:
            self.cameras = {DEFAULT_CAMERA: self.camera}
        elif next(iter(self.cameras.values())) is not self.camera:
            raise ValueError("Rig: `camera` must be the first (reference) of `cameras`")

    @property
    def reference(self) -> str:
        """The reference camera's name (extrinsics of the others are relative to it)."""
        return next(iter(self.cameras))

    def settings_for(self, name: str) -> CameraSettings:
        """The settings a camera captures with: its own, else the rig's."""
        if name not in self.cameras:
            raise KeyError(f"camera {name!r}: the rig has {list(self.cameras)}")
        if name == self.reference:
            return self.settings
        return self.camera_settings.get(name, self.settings)

    def move_to(self, pose: RobotPose) -> RobotPose:
        """Move the rig's mover to the flange pose `pose` within `move_timeout_s`; the pose
        it reports having reached (the `Mover` errors on failure)."""
        if self.mover is None:
            raise AcquisitionError("this rig has no mover: add a `mover` section to its "
                                   "config")
        return self.mover.move_to(pose, self.move_timeout_s)

    def close(self) -> None:
        """Stop and close the mover, close the cameras, the display and the trigger box
        (once)."""
        if self._closed:
            return
        self._closed = True
        for part in (self.mover, *self.cameras.values(), self.display, self.trigger):
            if part is not None:
                part.close()


SimulatorFactory = Callable[[RigConfig, Clock | None], Rig]


def _pitch(config: RigConfig) -> tuple[float, float]:
    p = config.screen.pitch_mm
    assert p is not None
    return (float(p), float(p)) if isinstance(p, int | float) else (float(p[0]), float(p[1]))


def open_display(cfg: FramebufferConfig | SdlConfig, clock: Clock) -> Display:
    """Open a real display backend from its config section."""
    if isinstance(cfg, FramebufferConfig):
        from acquisition.display.framebuffer import FramebufferDisplay, FramebufferGeometry

        geometry = None
        if cfg.width or cfg.height or cfg.bits_per_pixel:
            if not (cfg.width and cfg.height):
                raise RigConfigError("display: framebuffer geometry needs both width and height")
            geometry = FramebufferGeometry.standard(cfg.width, cfg.height,
                                                    cfg.bits_per_pixel or 32, cfg.line_length,
                                                    cfg.refresh_hz)
        return FramebufferDisplay(cfg.device, geometry=geometry, sysfs_root=cfg.sysfs_root,
                                  refresh_hz=cfg.refresh_hz, clock=clock)
    from acquisition.display.sdl import SdlDisplay

    size = (cfg.width, cfg.height) if cfg.width and cfg.height else None
    return SdlDisplay(cfg.monitor, size=size, refresh_hz=cfg.refresh_hz, vsync=cfg.vsync,
                      clock=clock, video_driver=cfg.video_driver)


def open_camera(cfg: OpenCvConfig | AravisConfig, clock: Clock) -> Camera:
    """Open a real camera backend from its config section."""
    if isinstance(cfg, OpenCvConfig):
        from acquisition.camera.opencv_capture import OpenCvCamera, is_recording
        from acquisition.camera.v4l2_controls import V4l2Controls

        controls = None
        src = cfg.source
        if cfg.v4l2_controls and not is_recording(src):
            controls = V4l2Controls(f"/dev/video{src}" if isinstance(src, int) else str(src))
        return OpenCvCamera(src, width=cfg.width, height=cfg.height, buffers=cfg.buffers,
                            replay_rate_hz=cfg.replay_rate_hz, clock=clock, controls=controls)
    from acquisition.camera.aravis_camera import AravisCamera

    return AravisCamera(cfg.device, buffers=cfg.buffers, bayer=cfg.bayer,
                        trigger_line=cfg.trigger_line, region=cfg.region, clock=clock)


def _with_mover(rig: Rig, config: RigConfig) -> Rig:
    """A simulated rig with its config's robot server (simulated movers come with the rig
    from the simulator); the rig is closed if the server cannot be reached."""
    if isinstance(config.mover, HttpMoverConfig):
        try:
            rig.mover = open_mover(config.mover)
        except BaseException:
            rig.close()
            raise
    if config.mover is not None:
        rig.move_timeout_s = config.mover.timeout_s
    return rig


def _check_extras(config: RigConfig) -> None:
    """Refuse a hardware rig whose backends' pip extras are missing, naming the command."""
    from calibration.extras import installed, missing_message

    needed = []
    if getattr(config.display, "backend", None) == "sdl":
        needed.append("sdl")
    if any(cfg.backend == "aravis" for _, cfg, _ in config.camera_entries()):
        needed.append("aravis")
    if config.trigger_box is not None:
        needed.append("usb")
    missing = [e for e in needed if not installed(e)]
    if missing:
        raise RigConfigError(missing_message(missing, f"rig {config.name or 'config'!r}"))


def open_rig(config: RigConfig, clock: Clock | None = None, *,
             simulator: SimulatorFactory | None = None) -> Rig:
    """Open every device of a rig; on failure, what was opened is closed again.

    Simulated rigs are made by `simulator` (the factory `hw_mocks` provides)."""
    if config.kind == "simulated":
        if simulator is None:
            raise RigConfigError("kind 'simulated': no simulator available here (pass "
                                 "hw_mocks.rig.open_simulated_rig as `simulator`)")
        return _with_mover(simulator(config, clock), config)
    _check_extras(config)
    clock = clock if clock is not None else RealClock()
    opened: list[Any] = []
    try:
        display = open_display(config.display, clock)  # type: ignore[arg-type]
        opened.append(display)
        cameras: dict[str, Camera] = {}
        for name, cfg, _ in config.camera_entries():
            cameras[name] = open_camera(cfg, clock)  # type: ignore[arg-type]
            opened.append(cameras[name])
        trigger = None
        if config.trigger_box is not None:
            from acquisition.usb.trigger_box import UsbTriggerBox

            tb = config.trigger_box
            trigger = UsbTriggerBox(tb.vendor_id, tb.product_id, serial=tb.serial,
                                    request=tb.request, index=tb.index)
            opened.append(trigger)
        mover = None
        if config.mover is not None:
            mover = open_mover(config.mover)  # type: ignore[arg-type]
            opened.append(mover)
        info = display.info
        screen = ScreenGeometry(config.screen.width_px or info.width_px,
                                config.screen.height_px or info.height_px, _pitch(config))
        if (screen.width_px, screen.height_px) != (info.width_px, info.height_px):
            raise RigConfigError(
                f"screen: {screen.width_px}x{screen.height_px} px in the config, the display "
                f"is {info.width_px}x{info.height_px}"
            )
        settings = config.settings.to_settings() if config.settings else CameraSettings()
        own = {name: st.to_settings() for name, _, st in config.camera_entries()[1:]
               if st is not None}
        first = config.camera_entries()[0]
        if first[2] is not None:
            settings = first[2].to_settings()
        return Rig(display, next(iter(cameras.values())), clock, settings, screen,
                   config=config, trigger=trigger, cameras=cameras, camera_settings=own,
                   mover=mover, move_timeout_s=config.mover.timeout_s if config.mover
                   else MoverBase.model_fields["timeout_s"].default)
    except BaseException:
        for part in reversed(opened):
            part.close()
        raise
