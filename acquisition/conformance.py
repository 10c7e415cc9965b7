"""The device conformance kit: checks every `Display` / `Camera` implementation must pass.

Shipped with the code (not only the tests) so a new backend, in this repository or outside
it, is checked the same way: call `check_display(display, clock)` and
`check_camera(camera, clock)` from its tests; they raise AssertionError naming the broken
rule. Used here for the simulated, framebuffer, SDL, OpenCV and Aravis backends.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from acquisition.clock import Clock
from acquisition.errors import CameraTimeout, DeviceSettingsError, DisplayError
from acquisition.protocols import Camera, CameraSettings, Display


def check_display(display: Display, clock: Clock) -> None:
    """show() returns increasing flip times on the refresh grid, after the call; bad images fail."""
    info = display.info
    assert info.width_px > 0 and info.height_px > 0 and info.refresh_hz > 0
    dtype = np.uint8 if info.bit_depth == 8 else np.uint16
    img = np.zeros((info.height_px, info.width_px), dtype)
    period = 1.0 / info.refresh_hz
    flips = []
    for level in (0, 128, 255):
        t_call = clock.now()
        flip = display.show(img + np.asarray(level, dtype))
        assert flip >= t_call - 1e-6, "flip time must not precede the show() call"
        assert clock.now() >= flip - 1e-3, "show() must block until the flip"
        flips.append(flip)
    gaps = np.diff(flips) / period
    assert np.all(gaps > 0.5), f"two flips within one refresh period: {gaps}"
    assert np.allclose(gaps, np.round(gaps), atol=0.25), f"flips off the vsync grid: {gaps}"
    with _raises((DisplayError, ValueError)):
        display.show(np.zeros((info.height_px + 1, info.width_px), dtype))


def check_camera(camera: Camera, clock: Clock, settings: CameraSettings | None = None) -> None:
    """configure/start/grab/flush/stop obey the contract; bad settings give DeviceSettingsError."""
    info = camera.info
    base = settings or CameraSettings(exposure_s=0.005, pixel_format=info.pixel_formats[0],
                                      trigger_mode=info.trigger_modes[0])
    with _raises(DeviceSettingsError, match="exposure"):
        camera.configure(CameraSettings(exposure_s=-1.0, pixel_format=base.pixel_format,
                                        trigger_mode=base.trigger_mode))
    with _raises(DeviceSettingsError, match="pixel_format"):
        camera.configure(CameraSettings(exposure_s=base.exposure_s, pixel_format="Bogus99",
                                        trigger_mode=base.trigger_mode))
    applied = camera.configure(base)
    assert applied.exposure_s > 0
    camera.start()
    try:
        t0 = clock.now()
        camera.flush()
        if applied.trigger_mode == "software":
            camera.trigger()
        frame = camera.grab(timeout_s=2.0)
        assert frame.image.shape == (info.height, info.width)
        assert frame.image.dtype in (np.uint8, np.uint16)
        assert frame.timestamp_s >= t0 - 1e-3, "frame after flush() started before the flush"
        if applied.trigger_mode == "software":
            camera.trigger()
        second = camera.grab(timeout_s=2.0)
        # (a frame counter may be 16 bits, GigE Vision's block id: wrap-aware)
        assert 0 < (second.sequence - frame.sequence) % 65536 < 32768, "sequence not advanced"
        if applied.trigger_mode == "software":  # triggered after the first frame arrived
            assert second.timestamp_s > frame.timestamp_s
        # (free-running, mapped times are upper bounds: a late first frame can be dated
        # after the next one, see acquisition/camera/aravis_camera.py; the sequence orders them)
        if applied.trigger_mode == "software":
            t1 = clock.now()
            with _raises(CameraTimeout):
                camera.grab(timeout_s=0.05)  # nothing triggered: must time out, not hang
            assert clock.now() - t1 < 1.0
    finally:
        camera.stop()


@contextmanager
def _raises(expected: type[BaseException] | tuple[type[BaseException], ...],
            match: str | None = None) -> Iterator[None]:
    """Assert that the block raises `expected` (with `match` in its message); no pytest needed."""
    try:
        yield
    except expected as exc:
        if match is not None and not re.search(match, str(exc)):
            raise AssertionError(f"{type(exc).__name__} without {match!r}: {exc}") from exc
        return
    raise AssertionError(f"expected {expected} to be raised")
