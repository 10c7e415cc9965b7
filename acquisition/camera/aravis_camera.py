"""Aravis (GenICam: GigE Vision, USB3 Vision) camera through GObject introspection.

Open by device id or address (never by discovery here), choose the pixel format
(Mono8/10/12/16, packed and Bayer formats decoded to grey), exposure and gain with auto
modes off and read back, frame rate, software or hardware trigger. Frames come from a
pool of stream buffers; every wait has a timeout, frames exposed before the last trigger
or flush are dropped (never returned stale), software triggers sent while a frame is
still due are held back and sent when it arrives (cameras ignore overlapping triggers),
and a lost control channel surfaces as `CameraDisconnected` so that `reconnect()` can
reopen the device with the same settings.

GigE Vision links drop packets (a busy switch or host). The stream asks the camera to
resend missing packets (GVSP packet resend, where the camera offers it) and gives a frame
up `frame_retention_s` after its last packet arrived. An incomplete buffer is recycled;
in a triggered mode it means the frame of a trigger is gone, so `grab` raises `FrameLost`
at once (the caller triggers again) instead of waiting for a frame that will never come.
`stream_statistics()` counts received, missing and resent packets and incomplete frames.

Device timestamps (ns, start of frame) are mapped to the controller's clock by the
smallest observed (arrival - device time) offset over recent frames, the arrival dated
by the host's reception timestamp: a mapped time is never earlier than the true one, so
a frame exposed after a trigger always passes the staleness check, and one exposed
before it is caught even if it is the first frame seen. Each mapped time is an upper
bound, not a clock in step with the device: right after a frame that arrived late (a
stream's first frames, a loaded host) the next frame can be dated before it; `sequence`
orders frames (dating it later instead would let a stale frame pass the check).
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import replace
from typing import Any

import numpy as np

from acquisition.camera.aravis_gi import GLib, aravis
from acquisition.camera.pixel_formats import PIXEL_FORMATS, decode_image, pixel_format
from acquisition.clock import Clock, RealClock
from acquisition.errors import (
    CameraDisconnected,
    CameraError,
    CameraTimeout,
    DeviceSettingsError,
    FrameLost,
)
from acquisition.protocols import CameraInfo, CameraSettings, Frame, TriggerMode
from acquisition.stream_statistics import StreamStatistics

# How many recent frames the device-to-clock offset is estimated from.
OFFSET_WINDOW = 64
# Relative tolerance on exposure read-back (devices round to their own increments).
EXPOSURE_TOLERANCE = 0.02
# Aravis stream counters (`ArvStream` infos) -> `StreamStatistics` fields; a stream type
# without one of them (USB3 Vision has no packets) leaves that count at 0.
STREAM_INFOS = {
    "n_completed_buffers": "completed_frames",
    "n_failures": "incomplete_frames",
    "n_missing_frames": "missing_frames",
    "n_received_packets": "received_packets",
    "n_missing_packets": "missing_packets",
    "n_resend_requests": "resend_requests",
    "n_resent_packets": "resent_packets",
}


class AravisCamera:
    """A `Camera` on one GenICam device opened by id (`Vendor-Model-Serial`) or address."""

    def __init__(
        self,
        device: str,
        *,
        buffers: int = 8,
        bayer: str = "demosaic",
        trigger_line: str = "Line0",
        region: tuple[int, int, int, int] | None = None,
        clock: Clock | None = None,
        packet_resend: bool = True,
        packet_timeout_s: float = 0.02,
        frame_retention_s: float = 0.2,
    ) -> None:
        if not device:
            raise DeviceSettingsError(
                "Aravis camera: give a device id or address (discovery is never implicit)"
            )
        if buffers < 2:
            raise DeviceSettingsError(f"Aravis camera: buffers must be >= 2, got {buffers}")
        if not 0 < packet_timeout_s < frame_retention_s:
            raise DeviceSettingsError(
                f"Aravis camera: need 0 < packet_timeout_s < frame_retention_s, got "
                f"{packet_timeout_s} and {frame_retention_s} (a resend needs time to arrive)"
            )
        self._Aravis = aravis()
        self.device = device
        self._buffers = buffers
        self._bayer = bayer
        self._trigger_line = trigger_line
        self._region = region  # (x, y, width, height) of the sensor to read; None: as is
        self._clock = clock if clock is not None else RealClock()
        # GigE Vision streams: ask for lost packets again after `packet_timeout_s`, give
        # a frame up `frame_retention_s` after its last packet (Aravis: 20 ms / 100 ms; a
        # longer retention keeps a frame whose sender stalled on a loaded host)
        self._packet_resend = packet_resend
        self._packet_timeout_s = packet_timeout_s
        self._frame_retention_s = frame_retention_s
        self._stats_before = StreamStatistics()  # counts of the streams already released
        self._resending = False  # whether the current stream asks for resends
        BufferStatus = self._Aravis.BufferStatus
        self._not_sent = (BufferStatus.CLEARED, BufferStatus.ABORTED, BufferStatus.UNKNOWN,
                          BufferStatus.FILLING)
        self._lost = threading.Event()
        self._offsets: collections.deque[float] = collections.deque(maxlen=OFFSET_WINDOW)
        self._not_before = -np.inf
        self._stream: Any = None
        self._running = False
        self.incomplete_buffers = 0
        self.stale_frames = 0
        self._outstanding = 0  # software triggers sent whose frames have not arrived yet
        self._deferred = 0  # software triggers held back until those frames arrive
        self._voided = 0  # of the outstanding triggers, those sent before the last flush
        self._open()
        self._settings = self._read_settings()

    # -- opening -------------------------------------------------------------------
    def _open(self) -> None:
        try:
            self._cam = self._Aravis.Camera.new(self.device)
        except GLib.Error as exc:
            raise CameraDisconnected(
                f"Aravis camera {self.device!r}: cannot open ({exc.message}); check the "
                "address/id, cabling and that no other program holds the camera"
            ) from exc
        self._lost.clear()
        dev = self._cam.get_device()
        dev.connect("control-lost", lambda *_: self._lost.set())
        if self._region is not None:
            try:
                self._cam.set_region(*self._region)
            except GLib.Error as exc:
                raise DeviceSettingsError(
                    f"Aravis camera {self.device}: region {self._region} rejected ({exc.message})"
                ) from exc
        _, _, w, h = self._cam.get_region()
        if self._region is not None and (w, h) != tuple(self._region[2:]):
            raise DeviceSettingsError(
                f"Aravis camera {self.device}: region {self._region} gives {w}x{h} "
                f"(sensor {self._cam.get_sensor_size()}, size increments apply)"
            )
        formats = tuple(
            f for f in (self._cam.dup_available_pixel_formats_as_strings() or [])
            if f in PIXEL_FORMATS
        )
        sources = self._cam.dup_available_trigger_sources() or []
        modes: list[TriggerMode] = ["free-running"]
        if "Software" in sources:
            modes.append("software")
        if any(s.startswith("Line") for s in sources):
            modes.append("hardware")
        fmt = pixel_format(self._cam.get_pixel_format_as_string())
        self._info = CameraInfo(
            name=f"{self._cam.get_vendor_name()} {self._cam.get_model_name()}",
            serial=self._cam.get_device_serial_number() or "",
            width=w, height=h, bit_depth=fmt.bit_depth,
            pixel_formats=formats, trigger_modes=tuple(modes),
        )

    def _read_settings(self) -> CameraSettings:
        c = self._cam
        return CameraSettings(
            exposure_s=c.get_exposure_time() * 1e-6,
            gain_db=c.get_gain(),
            pixel_format=c.get_pixel_format_as_string(),
            trigger_mode=self._trigger_mode_now(),
            frame_rate_hz=c.get_frame_rate() if c.is_frame_rate_available() else None,
        )

    def _trigger_mode_now(self) -> TriggerMode:
        try:
            if self._cam.get_string("TriggerMode") != "On":
                return "free-running"
        except GLib.Error:
            return "free-running"
        return "software" if self._cam.get_trigger_source() == "Software" else "hardware"

    @property
    def info(self) -> CameraInfo:
        return self._info

    # -- settings -------------------------------------------------------------------
    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Apply settings (auto exposure/gain off first) and return the read-back values."""
        was_running = self._running
        if was_running:
            self.stop()
        try:
            self._apply(settings)
        except GLib.Error as exc:
            raise self._error(f"configure({settings})", exc) from exc
        applied = replace(self._read_settings(), extra=dict(settings.extra))
        want, got = settings.exposure_s, applied.exposure_s
        if abs(got - want) > EXPOSURE_TOLERANCE * want + 1e-6:
            raise DeviceSettingsError(
                f"Aravis camera {self.device}: exposure_s {want} did not take effect "
                f"(device reports {got:.6f} s; bounds {self._cam.get_exposure_time_bounds()} us)"
            )
        if applied.trigger_mode != settings.trigger_mode:
            raise DeviceSettingsError(
                f"Aravis camera {self.device}: trigger_mode {settings.trigger_mode!r} did not "
                f"take effect (device reports {applied.trigger_mode!r})"
            )
        self._settings = applied
        fmt = pixel_format(applied.pixel_format)
        self._info = replace(self._info, bit_depth=fmt.bit_depth)
        if was_running:
            self.start()
        return applied

    def _apply(self, s: CameraSettings) -> None:
        c = self._cam
        if s.pixel_format not in self._info.pixel_formats:
            raise DeviceSettingsError(
                f"Aravis camera {self.device}: pixel_format {s.pixel_format!r} not offered; "
                f"choose one of {list(self._info.pixel_formats)}"
            )
        if s.trigger_mode not in self._info.trigger_modes:
            raise DeviceSettingsError(
                f"Aravis camera {self.device}: trigger_mode {s.trigger_mode!r} not supported; "
                f"choose one of {list(self._info.trigger_modes)}"
            )
        c.set_pixel_format_from_string(s.pixel_format)
        if c.is_exposure_auto_available():
            c.set_exposure_time_auto(self._Aravis.Auto.OFF)
        lo, hi = c.get_exposure_time_bounds()
        if not lo <= s.exposure_s * 1e6 <= hi:
            raise DeviceSettingsError(
                f"Aravis camera {self.device}: exposure_s {s.exposure_s} outside "
                f"[{lo * 1e-6:g}, {hi * 1e-6:g}] s"
            )
        c.set_exposure_time(s.exposure_s * 1e6)
        if c.is_gain_auto_available():
            c.set_gain_auto(self._Aravis.Auto.OFF)
        if c.is_gain_available():
            glo, ghi = c.get_gain_bounds()
            if not glo <= s.gain_db <= ghi:
                raise DeviceSettingsError(
                    f"Aravis camera {self.device}: gain_db {s.gain_db} outside [{glo}, {ghi}]"
                )
            c.set_gain(s.gain_db)
        if s.frame_rate_hz and c.is_frame_rate_available():
            # Free-running: the rate; triggered: the cap on the trigger rate (and the
            # polling rate of simple devices such as Aravis' fake camera). Set before the
            # trigger: Aravis turns TriggerMode off when setting a generic frame rate.
            c.set_frame_rate(s.frame_rate_hz)
        if s.trigger_mode == "software":
            c.set_trigger("Software")
        elif s.trigger_mode == "hardware":
            c.set_trigger(str(s.extra.get("trigger_line", self._trigger_line)))
        else:
            c.clear_triggers()
            c.set_acquisition_mode(self._Aravis.AcquisitionMode.CONTINUOUS)

    # -- streaming ------------------------------------------------------------------
    def start(self) -> None:
        """Allocate the stream buffers and start acquisition."""
        if self._running:
            return
        try:
            self._stream = self._cam.create_stream(None, None)
            self._tune_stream(self._stream)
            payload = self._cam.get_payload()
            for _ in range(self._buffers):
                self._stream.push_buffer(self._Aravis.Buffer.new_allocate(payload))
            self._cam.start_acquisition()
        except GLib.Error as exc:
            raise self._error("start", exc) from exc
        self._not_before = self._clock.now()
        self._outstanding, self._deferred, self._voided = 0, 0, 0
        self._running = True

    def _tune_stream(self, stream: Any) -> None:
        """GigE Vision: packet resend on (unless the camera cannot resend: Aravis turns it
        off for such cameras when it creates the stream) and the resend timings."""
        A = self._Aravis
        if not isinstance(stream, A.GvStream):
            self._resending = False
            return
        offered = stream.get_property("packet-resend") == A.GvStreamPacketResend.ALWAYS
        self._resending = self._packet_resend and offered
        stream.set_property("packet-resend", A.GvStreamPacketResend.ALWAYS if self._resending
                            else A.GvStreamPacketResend.NEVER)
        stream.set_property("packet-timeout", int(self._packet_timeout_s * 1e6))
        stream.set_property("frame-retention", int(self._frame_retention_s * 1e6))

    def _read_stream(self, stream: Any) -> StreamStatistics:
        """The counters of one stream (all zero for counters its type does not keep)."""
        counts = dict.fromkeys(STREAM_INFOS.values(), 0)
        for i in range(stream.get_n_infos()):
            field = STREAM_INFOS.get(stream.get_info_name(i))
            if field is not None:
                counts[field] = int(stream.get_info_uint64(i))
        return StreamStatistics(**counts, packet_resend=self._resending)

    def stream_statistics(self) -> StreamStatistics:
        """Transfer counters since the camera was opened, over every stream started."""
        if self._stream is None:
            return self._stats_before
        return self._stats_before.plus(self._read_stream(self._stream))

    def stop(self) -> None:
        """Stop acquisition and release the stream (buffers are freed with it)."""
        if not self._running:
            return
        self._running = False
        try:
            self._cam.stop_acquisition()
        except GLib.Error:
            pass  # the device may be gone; the stream is released anyway
        if self._stream is not None:
            self._stats_before = self.stream_statistics()
        self._stream = None

    def trigger(self) -> None:
        """Software trigger (hardware mode: the line fires; free-running: nothing to do)."""
        if not self._running:
            raise CameraError(f"Aravis camera {self.device}: trigger() before start()")
        t = self._clock.now()
        self._not_before = max(self._not_before, t)
        if self._settings.trigger_mode != "software":
            return
        if self._lost.is_set():
            raise CameraDisconnected(f"Aravis camera {self.device}: control channel lost")
        if self._outstanding:
            # Cameras ignore triggers while exposing or reading out (trigger overlap):
            # hold this one back and send it when the pending frame has arrived.
            self._deferred += 1
            return
        self._send_trigger()

    def _send_trigger(self) -> None:
        try:
            self._cam.software_trigger()
        except GLib.Error as exc:
            raise self._error("software trigger", exc) from exc
        self._outstanding += 1

    def _to_clock(self, device_ns: int, system_ns: int, popped: float, popped_ns: int) -> float:
        """Device time -> clock time; `system_ns` (host wall time at reception) dates the
        arrival even when the buffer waited in the queue before being popped (`popped` on
        the clock, `popped_ns` on the wall clock, read just before it)."""
        arrived = popped
        if system_ns > 0:
            arrived = popped - max(0.0, (popped_ns - system_ns) * 1e-9)
        if device_ns <= 0:
            return arrived - self._settings.exposure_s
        self._offsets.append(arrived - device_ns * 1e-9)
        return device_ns * 1e-9 + min(self._offsets)

    def grab(self, timeout_s: float) -> Frame:
        """Next good frame exposed after the last trigger/flush, within `timeout_s`."""
        if not self._running or self._stream is None:
            raise CameraError(f"Aravis camera {self.device}: grab() before start()")
        deadline = self._clock.now() + timeout_s
        while True:
            remaining = deadline - self._clock.now()
            if remaining <= 0:
                # lost triggers: start afresh
                self._outstanding, self._deferred, self._voided = 0, 0, 0
                self._check_alive()
                stats = self.stream_statistics()
                raise CameraTimeout(
                    f"Aravis camera {self.device}: no frame within {timeout_s:.3f} s "
                    f"(trigger mode {self._settings.trigger_mode}; so far "
                    f"{self.incomplete_buffers} incomplete buffers, {stats.missing_frames} "
                    f"frames missing, {stats.missing_packets} packets missing, "
                    f"{self.stale_frames} stale frames dropped)"
                )
            buf = self._stream.timeout_pop_buffer(max(1, int(min(remaining, 0.1) * 1e6)))
            if buf is None:
                if self._lost.is_set():
                    raise CameraDisconnected(f"Aravis camera {self.device}: control channel lost")
                continue
            frame = self._accept(buf)
            if frame is not None:
                return frame

    def _accept(self, buf: Any) -> Frame | None:
        """A popped buffer -> its frame; None if stale (or incomplete while free-running);
        `FrameLost` if it is a triggered frame that came back incomplete."""
        # both clocks read now, wall time first: a delay between the readings can only
        # date the arrival later (mapped times stay upper bounds); read after decoding,
        # a loaded host's delay dated it early and made fresh frames look stale
        popped_ns = time.time_ns()
        arrived = self._clock.now()
        status = buf.get_status()
        if status in self._not_sent:  # never filled: Aravis gave back a buffer it could not
            # use (a stray or unknown packet); no frame of the camera, no trigger answered
            self.incomplete_buffers += 1
            self._stream.push_buffer(buf)
            return None
        # frames answer the software triggers sent, in order: is a trigger still waiting
        # for this one? (an incomplete buffer cannot tell by its time: a buffer whose
        # leader packet was lost keeps the timestamp of the frame it held before)
        awaited = self._outstanding > self._voided
        self._voided = max(0, self._voided - 1)
        self._outstanding = max(0, self._outstanding - 1)  # stale or not, it answered one
        if self._deferred and not self._outstanding:
            self._deferred -= 1
            self._send_trigger()
        try:
            if status != self._Aravis.BufferStatus.SUCCESS:
                self.incomplete_buffers += 1
                mode = self._settings.trigger_mode
                if mode == "free-running" or (mode == "software" and not awaited):
                    return None  # the next frame is already on its way, or none is awaited
                stats = self.stream_statistics()
                resend = ("packet resend on" if self._resending else "packet resend off"
                          if not self._packet_resend else "the camera cannot resend")
                raise FrameLost(  # (no frame id: the lost packet may be the leader holding it)
                    f"Aravis camera {self.device}: a triggered frame arrived incomplete "
                    f"({status.value_nick}; so far {stats.missing_packets} packets missing, "
                    f"{stats.resent_packets} resent, {resend}); trigger again"
                )
            w, h = buf.get_image_width(), buf.get_image_height()
            fmt = pixel_format(buf.get_image_pixel_format())
            image = decode_image(buf.get_data(), fmt, w, h, self._bayer)
            t = self._to_clock(buf.get_timestamp(), buf.get_system_timestamp(), arrived,
                               popped_ns)
            seq = buf.get_frame_id()
        finally:
            self._stream.push_buffer(buf)
        if t < self._not_before:
            self.stale_frames += 1
            return None
        return Frame(image, t, self._settings.exposure_s, int(seq))

    def flush(self) -> int:
        """Return every queued buffer to the pool; later frames start after this call."""
        if self._stream is None:
            return 0
        n = 0
        while (buf := self._stream.try_pop_buffer()) is not None:
            self._stream.push_buffer(buf)
            n += 1
        self._deferred = 0  # triggers asked for before the flush are void
        self._voided = self._outstanding  # and so are the frames of those already sent
        self._not_before = max(self._not_before, self._clock.now())
        return n

    def _check_alive(self) -> None:
        """Read a register: a camera that cannot answer is reported as disconnected."""
        if self._lost.is_set():
            raise CameraDisconnected(f"Aravis camera {self.device}: control channel lost")
        try:
            self._cam.get_device().get_integer_feature_value("Width")
        except GLib.Error as exc:
            self._lost.set()
            raise CameraDisconnected(
                f"Aravis camera {self.device}: not answering ({exc.message}); reconnect()"
            ) from exc

    def _error(self, what: str, exc: Any) -> CameraError:
        if self._lost.is_set() or "timeout" in str(exc).lower():
            return CameraDisconnected(f"Aravis camera {self.device}: {what}: {exc}")
        return DeviceSettingsError(f"Aravis camera {self.device}: {what}: {exc}")

    def reconnect(self) -> None:
        """Reopen the device and restore settings (and streaming if it was on)."""
        running = self._running
        self.stop()
        self._cam = None
        self._open()
        self.configure(self._settings)
        if running:
            self.start()

    def close(self) -> None:
        self.stop()
        self._cam = None
