"""Simulated camera: triggered or free-running with a driver queue, timing faults, lazy rendering.

Frames are rendered on `grab` from the display's history: the light each screen row
emitted over the exposure window (a time-weighted mix when the exposure straddles a
change) goes through the optics (`OpticalSetup`) and the sensor (`SensorModel`).
Ground truth of every delivered frame (which display images, with which weights) is
kept in `truth`.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from acquisition.clock import Clock
from acquisition.errors import CameraDisconnected, CameraTimeout, DeviceSettingsError, FrameLost
from acquisition.protocols import CameraInfo, CameraSettings, Frame, TriggerMode
from hw_mocks.display import SimulatedDisplay
from hw_mocks.optics import OpticalSetup
from hw_mocks.sensor import SensorModel

PIXEL_FORMATS = {"Mono8": 8, "Mono12": 12, "Mono16": 16}


@dataclass
class CameraFaults:
    """Faults to inject; counters are 1-based (the n-th frame delivered, grab call, trigger)."""

    unplug_after_frames: int | None = None  # disconnect after this many delivered frames
    reconnect_failures: int = 0  # reconnect() attempts that fail before one succeeds
    timeout_grabs: frozenset[int] = frozenset()  # grab calls that time out
    late_triggers: dict[int, float] = field(default_factory=dict)  # trigger n -> extra delay s
    drop_probability: float = 0.0  # random frames lost in transfer (sequence gaps)
    # triggers whose frame arrives incomplete (packets lost on the link): grab raises
    # `FrameLost` when it reaches that frame, as a GigE Vision backend does
    lost_triggers: frozenset[int] = frozenset()


@dataclass(frozen=True)
class FrameTruth:
    """What was on screen during one delivered frame's exposure."""

    sequence: int
    start_s: float
    end_s: float
    timestamp_s: float
    image_ids: tuple[int, ...]  # display image ids seen (ShownImage.image_id)
    weights: tuple[float, ...]  # their mean time weight over screen rows

    @property
    def pure(self) -> bool:
        """True when exactly one display image was on every row for the whole exposure."""
        return len(self.image_ids) == 1


@dataclass
class _Exposure:
    sequence: int
    start_s: float
    timestamp_s: float
    lost: bool = False  # arrives as an incomplete buffer (`CameraFaults.lost_triggers`)


class SimulatedCamera:
    """A `Camera` looking at a `SimulatedDisplay` through `OpticalSetup` and `SensorModel`."""

    def __init__(
        self,
        display: SimulatedDisplay,
        optics: OpticalSetup,
        sensor: SensorModel,
        clock: Clock,
        *,
        trigger_modes: tuple[TriggerMode, ...] = ("software", "free-running"),
        default_frame_rate_hz: float = 30.0,
        max_frame_rate_hz: float = 120.0,
        max_gain_db: float = 24.0,
        buffer_depth: int = 4,
        timestamp_jitter_s: float = 2e-4,
        trigger_latency_s: float = 1e-4,
        readout_s: float = 5e-3,
        seed: int = 0,
        faults: CameraFaults | None = None,
        name: str = "simulated camera",
        serial: str = "SIM0001",
        replay: bool = False,
    ) -> None:
        if buffer_depth < 1:
            raise DeviceSettingsError(f"buffer_depth: expected >= 1, got {buffer_depth}")
        formats = tuple(f for f, b in PIXEL_FORMATS.items() if b <= sensor.bit_depth)
        self._info = CameraInfo(name, serial, optics.camera.width, optics.camera.height,
                                sensor.bit_depth, formats, trigger_modes)
        self.display, self.optics, self.base_sensor, self.clock = display, optics, sensor, clock
        self.default_frame_rate_hz = default_frame_rate_hz
        self.max_frame_rate_hz = max_frame_rate_hz
        self.max_gain_db = max_gain_db
        self.buffer_depth = buffer_depth
        self.timestamp_jitter_s = timestamp_jitter_s
        self.trigger_latency_s = trigger_latency_s
        self.readout_s = readout_s
        self.faults = faults if faults is not None else CameraFaults()
        # replay: a frame showing exactly the same screen content as an earlier one (same
        # codes, exposure, gain, screen pose) is that earlier frame again, noise included:
        # benchmarks time the service, not the renderer (a first, untimed pass fills it);
        # a torn frame is made of rows of the replayed frames of the images it mixes
        self.replay: dict[tuple, np.ndarray] | None = {} if replay else None
        self.gain_drift_db = 0.0  # added to the configured gain (auto-gain drift injection)
        self.truth: dict[int, FrameTruth] = {}
        self._rng = np.random.default_rng(seed)
        self._events: list[tuple[int, Callable[[], None]]] = []
        self._settings = CameraSettings(frame_rate_hz=default_frame_rate_hz)
        self._sensor = sensor
        self._connected, self._running, self._closed = True, False, False
        self._queue: deque[_Exposure] = deque(maxlen=buffer_depth)
        self._pending: deque[_Exposure] = deque()
        self._seq = 0
        self._fr_t0 = 0.0
        self._fr_next = 0
        self._busy_until = -math.inf
        self.delivered = 0
        self._grabs = 0
        self._triggers = 0

    # -- protocol ---------------------------------------------------------------------
    @property
    def info(self) -> CameraInfo:
        """Size, bit depth, pixel formats and trigger modes."""
        return self._info

    @property
    def settings(self) -> CameraSettings:
        """The settings applied last."""
        return self._settings

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Validate and apply settings; one `DeviceSettingsError` naming the bad setting."""
        s = settings
        if not 0 < s.exposure_s <= 10.0:
            raise DeviceSettingsError(
                f"exposure_s: expected 0 < exposure <= 10 s, got {s.exposure_s}")
        if not 0.0 <= s.gain_db <= self.max_gain_db:
            raise DeviceSettingsError(
                f"gain_db: expected 0..{self.max_gain_db} dB, got {s.gain_db}")
        if s.pixel_format not in self._info.pixel_formats:
            raise DeviceSettingsError(
                f"pixel_format: {s.pixel_format!r} not supported by {self._info.name}; "
                f"choose one of {self._info.pixel_formats}")
        if s.trigger_mode not in self._info.trigger_modes:
            raise DeviceSettingsError(
                f"trigger_mode: {s.trigger_mode!r} not supported by {self._info.name}; "
                f"choose one of {self._info.trigger_modes}")
        fps = s.frame_rate_hz if s.frame_rate_hz is not None else self.default_frame_rate_hz
        if not 0 < fps <= self.max_frame_rate_hz:
            raise DeviceSettingsError(f"frame_rate_hz: expected 0 < rate <= "
                                      f"{self.max_frame_rate_hz}, got {fps}")
        if s.trigger_mode == "free-running" and s.exposure_s > 1.0 / fps:
            raise DeviceSettingsError(
                f"frame_rate_hz: {fps} Hz is too high for exposure_s {s.exposure_s} s "
                f"(at most {1.0 / s.exposure_s:.3f} Hz)")
        self._settings = replace(s, frame_rate_hz=fps)
        self._sensor = replace(self.base_sensor, bit_depth=PIXEL_FORMATS[s.pixel_format],
                               dn_per_e=None)
        self._reset_stream()
        return self._settings

    def start(self) -> None:
        """Start acquiring (free-running: the first exposure starts now)."""
        self._check_connected()
        self._reset_stream()
        self._running = True
        self._fr_t0 = self.clock.now()

    def stop(self) -> None:
        """Stop acquiring; queued frames are dropped."""
        self._running = False
        self._reset_stream()

    def trigger(self) -> None:
        """Software trigger: one exposure starts as soon as the sensor is free."""
        self._check_connected()
        if not self._running:
            raise CameraTimeout(f"{self._info.name}: trigger() before start()")
        if self._settings.trigger_mode != "software":
            raise DeviceSettingsError(f"trigger_mode: trigger() needs 'software', camera is in "
                                      f"{self._settings.trigger_mode!r}")
        self._triggers += 1
        delay = self.trigger_latency_s + self.faults.late_triggers.get(self._triggers, 0.0)
        start = max(self.clock.now() + delay, self._busy_until)
        self._busy_until = start + self._settings.exposure_s + 1e-4
        exp = self._new_exposure(start)
        exp.lost = self._triggers in self.faults.lost_triggers
        self._pending.append(exp)

    def grab(self, timeout_s: float) -> Frame:
        """Oldest queued frame; waits up to `timeout_s` for one."""
        self._check_connected()
        self._grabs += 1
        deadline = self.clock.now() + timeout_s
        if self._grabs in self.faults.timeout_grabs:
            self.clock.sleep_until(deadline)
            raise CameraTimeout(f"{self._info.name}: no frame within {timeout_s} s (injected)")
        while True:
            self._update(self.clock.now())
            if self._queue and self._queue[0].lost:
                exp = self._queue.popleft()
                raise FrameLost(f"{self._info.name}: frame {exp.sequence} arrived incomplete "
                                "(injected packet loss); trigger again")
            if self._queue:
                return self._deliver(self._queue.popleft())
            nxt = self._next_delivery()
            if nxt is None or nxt > deadline:
                self.clock.sleep_until(deadline)
                raise CameraTimeout(f"{self._info.name}: no frame within {timeout_s} s")
            self.clock.sleep_until(nxt)

    def flush(self) -> int:
        """Drop queued frames and exposures already started; returns how many were queued."""
        self._check_connected()
        now = self.clock.now()
        self._update(now)
        n = len(self._queue)
        self._queue.clear()
        while self._pending and self._pending[0].start_s < now:
            self._pending.popleft()
        if self._running and self._settings.trigger_mode == "free-running":
            self._fr_next = max(self._fr_next, math.ceil((now - self._fr_t0) * self._fps))
        return n

    def reconnect(self) -> None:
        """Re-open after an unplug; fails `faults.reconnect_failures` times first."""
        if self._closed:
            raise CameraDisconnected(f"{self._info.name}: closed")
        if self._connected:
            return
        if self.faults.reconnect_failures > 0:
            self.faults.reconnect_failures -= 1
            raise CameraDisconnected(f"{self._info.name}: reconnect failed (device not found)")
        self._connected = True
        self.faults.unplug_after_frames = None

    def close(self) -> None:
        """Release the camera."""
        self._closed, self._running, self._connected = True, False, False

    # -- simulation controls ----------------------------------------------------------
    @property
    def triggers_fired(self) -> int:
        """Software triggers received so far (`CameraFaults` counts triggers from 1)."""
        return self._triggers

    def at_frame(self, n: int, action: Callable[[], None]) -> None:
        """Run `action` just before the n-th frame delivered from now on (1-based) renders."""
        self._events.append((self.delivered + n, action))

    def unplug(self) -> None:
        """Disconnect now (as if the cable was pulled)."""
        self._connected, self._running = False, False
        self._reset_stream()

    # -- internals --------------------------------------------------------------------
    @property
    def _fps(self) -> float:
        """Applied free-running frame rate."""
        assert self._settings.frame_rate_hz is not None
        return self._settings.frame_rate_hz

    def _check_connected(self) -> None:
        """Raise `CameraDisconnected` while unplugged."""
        if not self._connected:
            raise CameraDisconnected(f"{self._info.name} ({self._info.serial}) is disconnected; "
                                     "call reconnect()")

    def _reset_stream(self) -> None:
        """Forget queued and pending exposures."""
        self._queue.clear()
        self._pending.clear()
        self._fr_next = 0
        self._busy_until = -math.inf

    def _new_exposure(self, start: float) -> _Exposure:
        """Next sequence number and a jittered timestamp for an exposure starting at `start`."""
        self._seq += 1
        ts = start + float(self._rng.normal(0.0, self.timestamp_jitter_s))
        return _Exposure(self._seq, start, ts)

    def _arrival(self, start: float) -> float:
        """When an exposure starting at `start` reaches the driver queue."""
        return start + self._settings.exposure_s + self.readout_s

    def _next_delivery(self) -> float | None:
        """Arrival time of the next frame, or None if none is coming."""
        if not self._running:
            return None
        if self._settings.trigger_mode == "free-running":
            return self._arrival(self._fr_t0 + self._fr_next / self._fps)
        return self._arrival(self._pending[0].start_s) if self._pending else None

    def _update(self, now: float) -> None:
        """Move exposures that have arrived by `now` into the driver queue (oldest dropped)."""
        if not self._running:
            return
        arrived: list[_Exposure] = []
        if self._settings.trigger_mode == "free-running":
            last = math.floor((now - self.readout_s - self._settings.exposure_s - self._fr_t0)
                              * self._fps + 1e-9)
            first = max(self._fr_next, last - self.buffer_depth + 1)
            self._seq += first - self._fr_next  # frames overwritten in the driver
            arrived = [self._new_exposure(self._fr_t0 + k / self._fps)
                       for k in range(first, last + 1)]
            self._fr_next = max(self._fr_next, last + 1)
        else:
            while self._pending and self._arrival(self._pending[0].start_s) <= now:
                arrived.append(self._pending.popleft())
        for exp in arrived:
            if self._rng.random() >= self.faults.drop_probability:
                self._queue.append(exp)

    def _replay_key(self, shown: list, weights: np.ndarray, exposure_s: float) -> tuple | None:
        """Replay cache key of a pure frame (one image on every row), else None."""
        if self.replay is None or len(shown) != 1:
            return None
        digest = shown[0].digest
        pose = self.optics.pose  # the whole screen pose and the stray light: the same
        # translation with another rotation, or a changed ambient, is another image
        return (digest, exposure_s, self._settings.gain_db + self.gain_drift_db,
                self._settings.pixel_format, id(self.optics), pose.rotation.tobytes(),
                pose.translation.tobytes(), float(self.optics.ambient))

    def _replay_torn(self, shown: list, weights: np.ndarray, exposure_s: float
                     ) -> np.ndarray | None:
        """Replay of a frame mixing images (a torn one), if every image it mixes was seen
        pure: each camera row from the replayed frame of the image that held the panel row
        at the same height longest during the exposure (a scan-out's horizontal tear),
        else None. Approximate content (the controller rejects such frames by timing),
        made by row copies: a benchmark whose frames sometimes tear must not time the
        simulator (a per-pixel blend took 16-210 ms at 5 MP, in the controller's thread)."""
        if self.replay is None or len(shown) < 2:
            return None
        frames = [self.replay.get(self._replay_key([s], weights[k:k + 1], exposure_s))
                  for k, s in enumerate(shown)]
        if any(f is None for f in frames):
            return None
        height = frames[0].shape[0]
        panel_row = np.arange(height) * weights.shape[1] // height
        holder = weights[:, panel_row].argmax(axis=0)
        torn = frames[0].copy()
        for k in range(1, len(frames)):
            rows = holder == k
            torn[rows] = frames[k][rows]
        return torn

    def _deliver(self, exp: _Exposure) -> Frame:
        """Render a frame, record its truth, fire due events and the unplug fault."""
        self.delivered += 1
        for _, action in [e for e in self._events if e[0] == self.delivered]:
            action()
        self._events = [e for e in self._events if e[0] > self.delivered]
        e = self._settings.exposure_s
        shown, weights = self.display.row_weights(exp.start_s, exp.start_s + e)
        self.truth[exp.sequence] = FrameTruth(
            exp.sequence, exp.start_s, exp.start_s + e, exp.timestamp_s,
            tuple(s.image_id for s in shown), tuple(float(w) for w in weights.mean(axis=1)))
        key = self._replay_key(shown, weights, e)
        image = self.replay.get(key) if key is not None else self._replay_torn(shown, weights, e)
        if image is None:
            light = self.display.emitted(exp.start_s, exp.start_s + e)
            irradiance = self.optics.render_irradiance(light)
            image = self._sensor.expose(irradiance, e,
                                        self._settings.gain_db + self.gain_drift_db, self._rng)
            if key is not None:
                self.replay[key] = image
        unplug = self.faults.unplug_after_frames
        if unplug is not None and self.delivered >= unplug:
            self.unplug()
        return Frame(image, exp.timestamp_s, e, exp.sequence)
