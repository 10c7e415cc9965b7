"""Every real backend against the shared device protocol suite (acquisition/conformance.py)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest

from acquisition import conformance as protocol
from acquisition.clock import RealClock
from acquisition.display.framebuffer import FramebufferDisplay, FramebufferGeometry
from tests.hw_aravis_support import fake_camera_lock, require_aravis


@pytest.fixture
def fb_display():
    geo = FramebufferGeometry.standard(64, 40, 32, refresh_hz=60.0)
    path = Path(tempfile.mktemp(prefix="phasecal-fb-", dir="/dev/shm"))
    path.write_bytes(bytes(geo.size_bytes))
    d = FramebufferDisplay(path, geometry=geo, clock=RealClock())
    yield d
    d.close()
    path.unlink(missing_ok=True)


def test_framebuffer_display(fb_display) -> None:
    protocol.check_display(fb_display, RealClock())


def test_sdl_display(monkeypatch) -> None:
    from acquisition.display.sdl import SdlDisplay

    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    clock = RealClock()
    d = SdlDisplay(0, size=(64, 40), refresh_hz=60.0, clock=clock)
    try:
        protocol.check_display(d, clock)
    finally:
        d.close()


def test_opencv_camera_free_running_replay(tmp_path: Path) -> None:
    from acquisition.camera.opencv_capture import OpenCvCamera
    from tests.acquisition.test_hw_opencv import write_ffv1

    frames = np.random.default_rng(0).integers(0, 256, (400, 24, 32)).astype(np.uint8)
    clock = RealClock()
    cam = OpenCvCamera(write_ffv1(tmp_path / "r.mkv", frames), replay_rate_hz=60.0,
                       clock=clock)
    try:
        protocol.check_camera(cam, clock)
    finally:
        cam.close()


def test_aravis_camera() -> None:
    require_aravis()
    from acquisition.camera.aravis_camera import AravisCamera
    from acquisition.camera.aravis_fake import FakeGigECamera

    clock = RealClock()
    with fake_camera_lock():
        fake = FakeGigECamera("PHASECAL-PROTO",
                              lambda r: np.full((r.height, r.width), 100, np.uint8))
        cam = AravisCamera("127.0.0.1", clock=clock, region=(0, 0, 64, 48))
        try:
            protocol.check_camera(cam, clock)
        finally:
            cam.close()
            fake.stop()


class _FreeRunningStub:
    """A free-running GigE-like camera: 16-bit frame counter, frames dated by the
    smallest arrival offset seen, so a late first frame is dated after the next one."""

    def __init__(self, clock: RealClock, sequences: list[int], dates: list[float]) -> None:
        from acquisition.protocols import CameraInfo

        self.info = CameraInfo("stub", "0", 8, 6, 8)
        self.clock, self.sequences, self.dates = clock, sequences, dates

    def configure(self, settings):
        from acquisition.errors import DeviceSettingsError

        if settings.exposure_s <= 0:
            raise DeviceSettingsError("exposure_s: must be > 0")
        if settings.pixel_format != "Mono8":
            raise DeviceSettingsError(f"pixel_format: {settings.pixel_format} not offered")
        return settings

    def start(self) -> None:
        self.t0, self.count = self.clock.now(), 0

    def flush(self) -> None:
        self.count = 0

    def grab(self, timeout_s: float):
        from acquisition.protocols import Frame

        i, self.count = self.count, self.count + 1
        return Frame(np.zeros((6, 8), np.uint8), self.t0 + self.dates[i], 0.005,
                     self.sequences[i])

    def stop(self) -> None:
        pass


@pytest.mark.parametrize("sequences, dates, good", [
    ([65535, 1], [0.010, 0.026], True),  # the block id wraps (GigE skips 0)
    ([65410, 65411], [0.010, 0.009986], True),  # late first frame: dated 14 us after
    ([7, 7], [0.010, 0.026], False),  # the counter did not advance
])
def test_free_running_order_is_checked_by_sequence(sequences, dates, good) -> None:
    """The kit orders free-running frames by their (wrap-aware) counter, not by their
    mapped times, which are upper bounds; a counter that does not advance still fails."""
    clock = RealClock()
    cam = _FreeRunningStub(clock, sequences, dates)
    if good:
        protocol.check_camera(cam, clock)
    else:
        with pytest.raises(AssertionError, match="sequence"):
            protocol.check_camera(cam, clock)
