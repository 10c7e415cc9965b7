"""The small, typed device protocols every display and camera backend implements.

Simulated devices (`hw_mocks`) and real backends (framebuffer, SDL, OpenCV, Aravis) obey
the same contract, including timing: all timestamps are on the controller's `Clock`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

import numpy as np

TriggerMode = Literal["software", "hardware", "free-running"]


@dataclass(frozen=True)
class DisplayInfo:
    """What the controller needs to know about a display."""

    name: str
    width_px: int
    height_px: int
    refresh_hz: float
    bit_depth: int = 8  # device code depth per channel (8 or 10)


@runtime_checkable
class Display(Protocol):
    """A screen that shows single-channel images at vsync.

    `show` submits an image of device codes (uint8 for 8-bit, uint16 for 10-bit),
    shape (height_px, width_px), and returns the clock time of the vsync at which the
    display starts scanning it out (the flip). The image reaches the panel `latency`
    refresh periods after that flip (unknown to the controller; measured by the setup
    helpers) and is fully visible one refresh period later (top-to-bottom scan-out).
    """

    @property
    def info(self) -> DisplayInfo: ...

    def show(self, image: np.ndarray) -> float: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class CameraInfo:
    """Static facts about an opened camera."""

    name: str
    serial: str
    width: int
    height: int
    bit_depth: int  # significant bits in delivered images (8, 10, 12, 16)
    pixel_formats: tuple[str, ...] = ("Mono8",)
    trigger_modes: tuple[TriggerMode, ...] = ("free-running",)


@dataclass(frozen=True)
class CameraSettings:
    """Settings the controller asks for; `Camera.configure` returns what was applied."""

    exposure_s: float = 0.010
    gain_db: float = 0.0
    pixel_format: str = "Mono8"
    trigger_mode: TriggerMode = "free-running"
    frame_rate_hz: float | None = None  # free-running rate; None = device default
    extra: dict[str, float | int | str] = field(default_factory=dict)


@dataclass(frozen=True)
class Frame:
    """One captured image with its timing on the controller's clock."""

    image: np.ndarray  # (H, W) uint8/uint16, grey
    timestamp_s: float  # start of exposure
    exposure_s: float
    sequence: int  # camera frame counter; gaps mean dropped frames


@runtime_checkable
class Camera(Protocol):
    """A grey-level camera, free-running or triggered.

    `grab` returns the next delivered frame (the oldest still queued in the driver for
    free-running cameras) or raises `CameraTimeout` / `CameraDisconnected`; it never
    blocks longer than `timeout_s`. `flush` drops everything queued so the next frame
    is guaranteed to start exposing after the call.
    """

    @property
    def info(self) -> CameraInfo: ...

    def configure(self, settings: CameraSettings) -> CameraSettings: ...

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def trigger(self) -> None: ...

    def grab(self, timeout_s: float) -> Frame: ...

    def flush(self) -> int: ...

    def reconnect(self) -> None: ...

    def close(self) -> None: ...


class SimulatorControls(Protocol):
    """What only a simulated rig can do: place the screen (on a real rig a person or a robot
    moves it). `Rig.simulated` holds one on simulated rigs and None on real ones."""

    def set_pose(self, rotation: np.ndarray, translation_mm: np.ndarray) -> None:
        """Move the screen: X_cam = R S + t, for the next captured frame."""
