"""OpenCV camera through the real cv2.VideoCapture on recordings, V4L2 logic injected."""

from __future__ import annotations

import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from acquisition.camera.opencv_capture import OpenCvCamera
from acquisition.camera.v4l2_controls import (
    CID_AUTOGAIN,
    CID_EXPOSURE_ABSOLUTE,
    CID_EXPOSURE_AUTO,
    CID_GAIN,
    VIDIOC_G_CTRL,
    VIDIOC_S_CTRL,
    V4l2Controls,
)
from acquisition.clock import RealClock
from acquisition.errors import CameraDisconnected, CameraTimeout, DeviceSettingsError
from acquisition.protocols import CameraSettings


def _frames(n: int, h: int, w: int, dtype) -> np.ndarray:
    rng = np.random.default_rng(5)
    top = np.iinfo(dtype).max
    return rng.integers(0, top + 1, size=(n, h, w)).astype(dtype)


def write_sequence(folder: Path, frames: np.ndarray) -> str:
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        assert cv2.imwrite(str(folder / f"frame_{i:04d}.png"), f)
    return str(folder / "frame_%04d.png")


def write_ffv1(path: Path, frames: np.ndarray) -> str:
    h, w = frames.shape[1:]
    vw = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), 30.0,
                         (w, h), True)
    assert vw.isOpened()
    for f in frames:
        vw.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    vw.release()
    return str(path)


def test_png_sequence_16bit_replays_exactly(tmp_path: Path) -> None:
    frames = _frames(4, 12, 10, np.uint16)
    cam = OpenCvCamera(write_sequence(tmp_path / "seq", frames))
    assert cam.info.bit_depth == 16 and cam.info.pixel_formats == ("Mono16",)
    applied = cam.configure(CameraSettings(pixel_format="Mono16", trigger_mode="software"))
    assert applied.pixel_format == "Mono16"
    cam.start()
    got = []
    for _ in range(4):
        cam.trigger()
        got.append(cam.grab(1.0))
    for f, want in zip(got, frames, strict=True):
        assert f.image.dtype == np.uint16
        np.testing.assert_array_equal(f.image, want)
    assert [f.sequence for f in got] == [1, 2, 3, 4]
    with pytest.raises(CameraTimeout, match="one frame per software trigger"):
        cam.grab(0.1)  # nothing triggered
    cam.trigger()
    with pytest.raises(CameraTimeout, match="recording exhausted after 4 frames"):
        cam.grab(0.1)
    cam.close()


def test_ffv1_video_replays_exactly_as_grey(tmp_path: Path) -> None:
    frames = _frames(5, 16, 24, np.uint8)
    cam = OpenCvCamera(write_ffv1(tmp_path / "rec.mkv", frames))
    cam.start()
    cam.trigger()
    cam.trigger()
    assert cam.flush() == 2  # triggered but never grabbed: dropped, never returned later
    for want in frames[2:]:
        cam.trigger()
        img = cam.grab(1.0).image
        assert img.ndim == 2 and img.dtype == np.uint8
        np.testing.assert_array_equal(img, want)
    cam.close()


def test_recording_settings_are_checked(tmp_path: Path) -> None:
    cam = OpenCvCamera(write_sequence(tmp_path / "s", _frames(1, 4, 4, np.uint8)))
    assert cam.info.trigger_modes == ("software",)
    with pytest.raises(DeviceSettingsError, match="trigger_mode 'free-running'"):
        cam.configure(CameraSettings(trigger_mode="free-running"))
    with pytest.raises(DeviceSettingsError, match="holds Mono8"):
        cam.configure(CameraSettings(pixel_format="Mono16", trigger_mode="software"))
    cam.close()
    with pytest.raises(CameraDisconnected, match="does not exist"):
        OpenCvCamera(str(tmp_path / "missing.mkv"))


def test_free_running_replay_flush_and_timeout(tmp_path: Path) -> None:
    frames = _frames(40, 8, 8, np.uint8)
    cam = OpenCvCamera(write_ffv1(tmp_path / "r.mkv", frames), replay_rate_hz=100.0,
                       buffers=2, clock=RealClock())
    assert cam.info.trigger_modes == ("free-running",)
    cam.configure(CameraSettings(exposure_s=0.001))
    cam.start()
    first = cam.grab(1.0)
    clock = RealClock()
    clock.sleep_until(clock.now() + 0.08)  # ~8 frames arrive, only 2 are kept
    t_flush = clock.now()
    cam.flush()
    nxt = cam.grab(1.0)
    assert nxt.timestamp_s >= t_flush  # never a frame exposed before the flush
    assert nxt.sequence > first.sequence + 1  # the queued (stale) ones were dropped
    np.testing.assert_array_equal(nxt.image, frames[nxt.sequence - 1])  # exact, in order
    with pytest.raises(CameraDisconnected, match="recording exhausted"):
        for _ in range(60):
            cam.grab(0.5)
    cam.close()


class FakeCapture:
    """A stand-in for cv2.VideoCapture on a V4L2 device: frames until 'unplugged'."""

    def __init__(self, frames: list[np.ndarray]) -> None:
        self.frames, self.props, self.unplugged = frames, {}, threading.Event()
        self.i = 0

    def isOpened(self) -> bool:
        return not self.unplugged.is_set()

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        if prop == cv2.CAP_PROP_FPS:
            return 200.0
        return float(self.props.get(prop, 0.0))

    def read(self):
        if self.unplugged.is_set():
            return False, None
        threading.Event().wait(0.005)
        self.i += 1
        return True, cv2.cvtColor(self.frames[self.i % len(self.frames)], cv2.COLOR_GRAY2BGR)

    def release(self) -> None:
        pass


def test_live_device_unplug_and_reconnect() -> None:
    frames = list(_frames(3, 6, 8, np.uint8))
    captures: list[FakeCapture] = []

    def factory(source, api):
        assert source == 0 and api == cv2.CAP_V4L2
        captures.append(FakeCapture(frames))
        return captures[-1]

    cam = OpenCvCamera(0, capture_factory=factory, width=8, height=6)
    assert captures[0].props[cv2.CAP_PROP_BUFFERSIZE] == 1
    assert captures[0].props[cv2.CAP_PROP_CONVERT_RGB] == 0
    applied = cam.configure(CameraSettings(exposure_s=0.002, extra={"gain_raw": 7}))
    assert applied.exposure_s == pytest.approx(0.002)
    assert captures[0].props[cv2.CAP_PROP_AUTO_EXPOSURE] == 1  # manual mode
    assert applied.extra["gain_raw"] == 7
    cam.start()
    assert cam.grab(1.0).image.shape == (6, 8)
    captures[0].unplugged.set()
    with pytest.raises(CameraDisconnected, match="consecutive failed reads"):
        for _ in range(100):
            cam.grab(1.0)
    cam.reconnect()
    assert len(captures) == 2 and captures[1].props[cv2.CAP_PROP_AUTO_EXPOSURE] == 1
    assert cam.grab(1.0).image.shape == (6, 8)
    cam.close()


def test_live_device_grab_times_out_instead_of_hanging() -> None:
    class Stuck(FakeCapture):
        def read(self):
            if self.i:
                threading.Event().wait(5.0)  # a driver that stops delivering
            self.i += 1
            return True, self.frames[0]

    cam = OpenCvCamera(0, capture_factory=lambda s, a: Stuck([np.zeros((4, 4), np.uint8)]))
    cam.start()
    cam.grab(0.5)  # the frame read at open
    with pytest.raises(CameraTimeout, match=r"no frame within 0\.200 s"):
        cam.grab(0.2)
    cam._running = False  # the stuck reader thread is a daemon; do not wait for it


class FakeV4l2:
    """Emulates VIDIOC_G_CTRL/S_CTRL of a UVC driver (exposure in 100 us, range-limited)."""

    def __init__(self, max_exposure_units: int = 5000) -> None:
        self.ctrl = {CID_EXPOSURE_AUTO: 3, CID_EXPOSURE_ABSOLUTE: 156, CID_AUTOGAIN: 1,
                     CID_GAIN: 10}
        self.log: list[tuple[int, int]] = []
        self.max = max_exposure_units

    def __call__(self, fd: int, request: int, buf: bytearray) -> int:
        import struct

        cid, value = struct.unpack("=Ii", buf)
        if cid not in self.ctrl:
            raise OSError(22, "Invalid argument")
        if request == VIDIOC_S_CTRL:
            if cid == CID_EXPOSURE_ABSOLUTE:
                if self.ctrl[CID_EXPOSURE_AUTO] != 1:
                    raise OSError(13, "Permission denied")  # auto exposure still on
                value = min(value, self.max)
            self.ctrl[cid] = value
            self.log.append((cid, value))
        else:
            assert request == VIDIOC_G_CTRL
        buf[:] = struct.pack("=Ii", cid, self.ctrl[cid])
        return 0


def test_v4l2_controls_auto_off_first_then_read_back() -> None:
    fake = FakeV4l2()
    ctl = V4l2Controls("/dev/video9", ioctl=fake, fd=-1)
    assert ctl.set_manual_exposure(0.0123) == pytest.approx(0.0123)
    assert fake.log[0] == (CID_EXPOSURE_AUTO, 1)
    assert fake.ctrl[CID_EXPOSURE_ABSOLUTE] == 123
    assert ctl.set_manual_gain(42) == 42 and fake.ctrl[CID_AUTOGAIN] == 0


def test_exposure_not_taking_effect_is_reported() -> None:
    fake = FakeV4l2(max_exposure_units=100)  # driver clamps to 10 ms
    ctl = V4l2Controls("/dev/video9", ioctl=fake, fd=-1)
    frames = [np.zeros((4, 4), np.uint8)]
    cam = OpenCvCamera(0, capture_factory=lambda s, a: FakeCapture(frames), controls=ctl)
    with pytest.raises(DeviceSettingsError, match=r"exposure_s 0.05 did not take effect"):
        cam.configure(CameraSettings(exposure_s=0.05))
    assert cam.configure(CameraSettings(exposure_s=0.005)).exposure_s == pytest.approx(0.005)
    with pytest.raises(DeviceSettingsError, match="no dB scale"):
        cam.configure(CameraSettings(gain_db=3.0))
    cam.close()
