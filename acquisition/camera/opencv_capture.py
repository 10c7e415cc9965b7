"""OpenCV `VideoCapture` camera: V4L2 devices, and recorded image sequences or videos.

Live devices (an index or `/dev/videoN`, `CAP_V4L2` on Linux) are free-running: a reader
thread keeps at most `buffers` frames (oldest dropped), so `grab` never blocks longer
than its timeout and `flush` guarantees the next frame started exposing after the call.
Exposure and gain are set with auto modes off and read back (V4L2 controls directly
when the device file is known). Recordings (`frame_%04d.png` with `CAP_IMAGES`, or a
lossless FFV1 `.mkv`) replay exactly, in order, as a software-triggered camera: each
`trigger()` "exposes" the next recorded frame at the trigger time, so the controller's
timing checks hold; set `replay_rate_hz` to replay them as a free-running camera
instead. Grey conversion keeps 16-bit data.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from acquisition.camera.v4l2_controls import V4l2Controls
from acquisition.clock import Clock, RealClock
from acquisition.errors import CameraDisconnected, CameraError, CameraTimeout, DeviceSettingsError
from acquisition.protocols import CameraInfo, CameraSettings, Frame, TriggerMode

# Camera pixel format -> V4L2 fourcc requested from the driver.
FOURCC = {"Mono8": "GREY", "Mono16": "Y16 ", "YUYV": "YUYV", "MJPG": "MJPG"}
# Consecutive failed reads of a live device before it is declared disconnected.
FAILED_READS_DISCONNECTED = 5

CaptureFactory = Callable[[str | int, int], Any]


def _default_factory(source: str | int, api: int) -> Any:
    return cv2.VideoCapture(source, api)


def is_recording(source: str | int) -> bool:
    """True for image-sequence patterns and video files (not devices)."""
    if isinstance(source, int) or str(source).startswith("/dev/video"):
        return False
    return "%" in str(source) or Path(source).suffix.lower() in (".mkv", ".avi", ".mp4", ".mov")


def to_grey(image: np.ndarray) -> np.ndarray:
    """Any OpenCV frame -> 2-D grey, keeping uint16 data (BGR/BGRA converted by luma)."""
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(image, code)
    raise CameraError(f"OpenCV camera: cannot convert frame of shape {image.shape} to grey")


class OpenCvCamera:
    """A `Camera` on `cv2.VideoCapture` (device or recording)."""

    def __init__(
        self,
        source: str | int,
        *,
        width: int | None = None,
        height: int | None = None,
        buffers: int = 2,
        replay_rate_hz: float | None = None,
        clock: Clock | None = None,
        capture_factory: CaptureFactory | None = None,
        controls: V4l2Controls | None = None,
        name: str | None = None,
    ) -> None:
        if buffers < 1:
            raise DeviceSettingsError(f"OpenCV camera: buffers must be >= 1, got {buffers}")
        self.source = source
        self._recording = is_recording(source)
        self._size = (width, height)
        self._buffers = buffers
        self._replay_rate = replay_rate_hz
        self._clock = clock if clock is not None else RealClock()
        self._factory = capture_factory or _default_factory
        self._controls = controls
        self._name = name or f"opencv {source}"
        self._settings = CameraSettings()
        self._lock = threading.Condition()
        self._queue: collections.deque[Frame] = collections.deque(maxlen=buffers)
        self._thread: threading.Thread | None = None
        self._running = False
        self._lost: str | None = None
        self._not_before = -np.inf
        self._seq = 0
        self._cap = self._open()
        self._pending = self._read_first()
        h, w = self._pending.shape
        depth = 16 if self._pending.dtype == np.uint16 else 8
        fmt = "Mono16" if depth == 16 else "Mono8"
        mode: TriggerMode = "free-running" if self._free_running else "software"
        self._info = CameraInfo(self._name, str(source), w, h, depth, (fmt,), (mode,))
        self._settings = CameraSettings(pixel_format=fmt, trigger_mode=mode)

    # -- opening -------------------------------------------------------------------
    def _api(self) -> int:
        if self._recording:
            return cv2.CAP_IMAGES if "%" in str(self.source) else cv2.CAP_FFMPEG
        return cv2.CAP_V4L2

    def _open(self) -> Any:
        if self._recording and "%" not in str(self.source) and not Path(self.source).is_file():
            raise CameraDisconnected(f"OpenCV camera: recording {self.source} does not exist")
        cap = self._factory(self.source, self._api())
        if not cap.isOpened():
            raise CameraDisconnected(
                f"OpenCV camera {self.source}: cannot open (no such device, busy, or no frames)"
            )
        if not self._recording:
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # minimal driver queue where supported
            cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)  # keep Y16 as 16-bit
            w, h = self._size
            if w:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, w)
            if h:
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, h)
        return cap

    def _read_first(self) -> np.ndarray:
        ok, img = self._cap.read()
        if not ok or img is None:
            self._cap.release()
            raise CameraDisconnected(f"OpenCV camera {self.source}: opened but delivers no frame")
        img = to_grey(img)
        w, h = self._size
        if (w and img.shape[1] != w) or (h and img.shape[0] != h):
            self._cap.release()
            raise DeviceSettingsError(
                f"OpenCV camera {self.source}: asked {w}x{h}, delivers "
                f"{img.shape[1]}x{img.shape[0]}"
            )
        return img

    @property
    def info(self) -> CameraInfo:
        return self._info

    # -- settings -------------------------------------------------------------------
    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Apply settings; returns what the device reports (recordings: what they hold)."""
        if not (np.isfinite(settings.exposure_s) and settings.exposure_s > 0):
            raise DeviceSettingsError(
                f"OpenCV camera {self.source}: exposure_s must be > 0 s, got {settings.exposure_s}"
            )
        if settings.trigger_mode not in self._info.trigger_modes:
            raise DeviceSettingsError(
                f"OpenCV camera {self.source}: trigger_mode {settings.trigger_mode!r} not "
                f"supported; this source is {self._info.trigger_modes[0]} (V4L2/UVC cameras "
                "free-running, recordings software-triggered unless replay_rate_hz is set)"
            )
        if settings.pixel_format not in self._info.pixel_formats and self._recording:
            raise DeviceSettingsError(
                f"OpenCV camera {self.source}: pixel_format {settings.pixel_format!r}: the "
                f"recording holds {self._info.pixel_formats[0]}"
            )
        if self._recording:
            self._settings = settings
            return settings
        return self._configure_device(settings)

    def _configure_device(self, s: CameraSettings) -> CameraSettings:
        cap = self._cap
        fourcc = FOURCC.get(s.pixel_format)
        if fourcc is None:
            raise DeviceSettingsError(
                f"OpenCV camera {self.source}: pixel_format {s.pixel_format!r}; choose one of "
                f"{sorted(FOURCC)}"
            )
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*fourcc))
        if s.frame_rate_hz:
            cap.set(cv2.CAP_PROP_FPS, s.frame_rate_hz)
        raw_gain = s.extra.get("gain_raw")
        if s.gain_db and raw_gain is None:
            raise DeviceSettingsError(
                f"OpenCV camera {self.source}: V4L2 gain has no dB scale; set gain_db = 0 and "
                "extra.gain_raw to a device gain value"
            )
        if self._controls is not None:
            exposure = self._controls.set_manual_exposure(s.exposure_s)
            gain = self._controls.set_manual_gain(None if raw_gain is None else int(raw_gain))
        else:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2 "manual mode" through OpenCV
            cap.set(cv2.CAP_PROP_EXPOSURE, round(s.exposure_s / 100e-6))
            exposure = cap.get(cv2.CAP_PROP_EXPOSURE) * 100e-6
            if raw_gain is not None:
                cap.set(cv2.CAP_PROP_GAIN, float(raw_gain))
            gain = cap.get(cv2.CAP_PROP_GAIN)
        if abs(exposure - s.exposure_s) > max(100e-6, 0.05 * s.exposure_s):
            raise DeviceSettingsError(
                f"OpenCV camera {self.source}: exposure_s {s.exposure_s} did not take effect "
                f"(device reports {exposure:.6f} s); is auto exposure locked on?"
            )
        got_fourcc = int(cap.get(cv2.CAP_PROP_FOURCC))
        got_fmt = "".join(chr((got_fourcc >> (8 * i)) & 0xFF) for i in range(4))
        fmt = next((k for k, v in FOURCC.items() if v == got_fmt), s.pixel_format)
        extra = dict(s.extra)
        if gain is not None:
            extra["gain_raw"] = int(gain)
        self._settings = replace(s, exposure_s=exposure, pixel_format=fmt, extra=extra)
        return self._settings

    # -- streaming ------------------------------------------------------------------
    @property
    def _free_running(self) -> bool:
        return not self._recording or self._replay_rate is not None

    def start(self) -> None:
        if self._running:
            return
        self._running = True
        if self._free_running:
            self._thread = threading.Thread(target=self._reader, name=f"opencv {self.source}",
                                            daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._running = False
        with self._lock:
            self._lock.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def trigger(self) -> None:
        """Recording replay: expose the next recorded frame now; free-running: nothing."""
        if self._free_running:
            return
        if not self._running:
            raise CameraError(f"OpenCV camera {self.source}: trigger() before start()")
        img = self._next_image()
        with self._lock:
            if img is None:
                self._lost = f"recording exhausted after {self._seq} frames"
                return
            self._seq += 1
            self._queue.append(Frame(img, self._clock.now(), self._settings.exposure_s,
                                     self._seq))

    def _frame_period(self) -> float:
        if self._replay_rate:
            return 1.0 / self._replay_rate
        fps = self._cap.get(cv2.CAP_PROP_FPS) if not self._recording else 0.0
        return 1.0 / fps if fps and fps > 0 else 1.0 / 30.0

    def _next_image(self) -> np.ndarray | None:
        if self._pending is not None:
            img, self._pending = self._pending, None
            return img
        ok, img = self._cap.read()
        return to_grey(img) if ok and img is not None else None

    def _make_frame(self, img: np.ndarray, arrived: float) -> Frame:
        # Exposure started about one exposure (plus one frame transfer for a live device)
        # before arrival.
        start = arrived - self._settings.exposure_s - (0.0 if self._recording else
                                                       self._frame_period())
        self._seq += 1
        return Frame(img, start, self._settings.exposure_s, self._seq)

    def _reader(self) -> None:
        failures = 0
        period = self._frame_period()
        next_t = self._clock.now()
        while self._running:
            if self._replay_rate:
                next_t += period
                self._clock.sleep_until(next_t)
            img = self._next_image()
            if img is None:
                failures += 1
                if self._recording or failures >= FAILED_READS_DISCONNECTED:
                    with self._lock:
                        self._lost = ("recording exhausted" if self._recording
                                      else f"{failures} consecutive failed reads")
                        self._lock.notify_all()
                    return
                continue
            failures = 0
            frame = self._make_frame(img, self._clock.now())
            with self._lock:
                self._queue.append(frame)
                self._lock.notify_all()

    def grab(self, timeout_s: float) -> Frame:
        """Oldest queued frame not older than the last flush (or the next recorded one)."""
        if not self._running:
            raise CameraError(f"OpenCV camera {self.source}: grab() before start()")
        if not self._free_running:
            with self._lock:
                if self._queue:
                    return self._queue.popleft()
            if self._lost is not None:
                raise CameraTimeout(f"OpenCV camera {self.source}: {self._lost}")
            raise CameraTimeout(
                f"OpenCV camera {self.source}: no frame (a recording replays one frame per "
                "software trigger)"
            )
        deadline = self._clock.now() + timeout_s
        with self._lock:
            while True:
                while self._queue:
                    frame = self._queue.popleft()
                    if frame.timestamp_s >= self._not_before:
                        return frame
                if self._lost is not None:
                    raise CameraDisconnected(
                        f"OpenCV camera {self.source}: lost ({self._lost}); call reconnect()"
                    )
                remaining = deadline - self._clock.now()
                if remaining <= 0 or not self._running:
                    raise CameraTimeout(
                        f"OpenCV camera {self.source}: no frame within {timeout_s:.3f} s"
                    )
                self._lock.wait(min(remaining, 0.05))

    def flush(self) -> int:
        """Drop queued frames; later frames must have started exposing after this call."""
        with self._lock:
            n = len(self._queue)
            self._queue.clear()
            self._not_before = self._clock.now()
        return n

    def reconnect(self) -> None:
        """Release and reopen the source, re-applying the last settings."""
        running = self._running
        self.stop()
        self._cap.release()
        with self._lock:
            self._queue.clear()
            self._lost = None
        self._cap = self._open()
        self._pending = self._read_first()
        if not self._recording:
            self._configure_device(self._settings)
        if running:
            self.start()

    def close(self) -> None:
        self.stop()
        self._cap.release()
        if self._controls is not None:
            self._controls.close()
