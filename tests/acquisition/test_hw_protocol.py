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
