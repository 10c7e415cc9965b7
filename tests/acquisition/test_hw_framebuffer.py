"""Framebuffer display on a file-backed framebuffer: bytes per pixel format, geometry, vsync."""

from __future__ import annotations

import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest

from acquisition.clock import RealClock
from acquisition.display.framebuffer import (
    Bitfield,
    FramebufferDisplay,
    FramebufferGeometry,
    geometry_from_sysfs,
    list_framebuffers,
    parse_fix_screeninfo,
    parse_var_screeninfo,
)
from acquisition.errors import DisplayError

SHM = Path("/dev/shm") if Path("/dev/shm").is_dir() else Path(tempfile.gettempdir())


@pytest.fixture
def fb_file(tmp_path: Path):
    """A file in /dev/shm the size of a framebuffer, removed afterwards."""
    made: list[Path] = []

    def make(size: int) -> Path:
        f = Path(tempfile.mktemp(prefix="phasecal-fb-", dir=SHM))
        f.write_bytes(b"\xEE" * size)
        made.append(f)
        return f

    yield make
    for f in made:
        f.unlink(missing_ok=True)


def _image(h: int, w: int, depth: int = 8) -> np.ndarray:
    rng = np.random.default_rng(3)
    img = rng.integers(0, 1 << depth, size=(h, w))
    img[0, 0], img[0, 1] = 0, (1 << depth) - 1
    return img.astype(np.uint8 if depth == 8 else np.uint16)


def test_xrgb8888_with_padded_stride(fb_file) -> None:
    h, w, stride = 5, 7, 7 * 4 + 12
    geo = FramebufferGeometry.standard(w, h, 32, stride, refresh_hz=240.0)
    path = fb_file(h * stride)
    img = _image(h, w)
    d = FramebufferDisplay(path, geometry=geo, clock=RealClock())
    d.show(img)
    d.close()
    raw = np.frombuffer(path.read_bytes(), np.uint8).reshape(h, stride)
    px = raw[:, : w * 4].reshape(h, w, 4)
    for ch in range(3):  # B, G, R bytes all equal the grey code; X byte untouched by design
        np.testing.assert_array_equal(px[:, :, ch], img)
    assert np.all(px[:, :, 3] == 0)  # no transparency bits: the 4th byte is written as 0
    assert np.all(raw[:, w * 4:] == 0xEE)  # padding after each row is never touched


def test_rgb888_24bpp(fb_file) -> None:
    h, w = 4, 6
    geo = FramebufferGeometry.standard(w, h, 24)
    path = fb_file(geo.size_bytes)
    img = _image(h, w)
    with_display = FramebufferDisplay(path, geometry=geo, refresh_hz=500.0)
    with_display.show(img)
    with_display.close()
    px = np.frombuffer(path.read_bytes(), np.uint8).reshape(h, w, 3)
    for ch in range(3):
        np.testing.assert_array_equal(px[:, :, ch], img)


def test_rgb565_16bpp_scales_each_channel(fb_file) -> None:
    h, w = 3, 5
    geo = FramebufferGeometry.standard(w, h, 16)
    path = fb_file(geo.size_bytes)
    img = _image(h, w)
    d = FramebufferDisplay(path, geometry=geo, refresh_hz=500.0)
    d.show(img)
    d.close()
    words = np.frombuffer(path.read_bytes(), "<u2").reshape(h, w).astype(np.int64)
    r, g, b = words >> 11, (words >> 5) & 0x3F, words & 0x1F
    code = img.astype(np.float64)
    np.testing.assert_array_equal(r, np.rint(code * 31 / 255))
    np.testing.assert_array_equal(g, np.rint(code * 63 / 255))
    np.testing.assert_array_equal(b, np.rint(code * 31 / 255))


def test_bgra_with_alpha_and_10bit_channels(fb_file) -> None:
    # A 30-bit (2:10:10:10) framebuffer: the display becomes a 10-bit display.
    h, w = 2, 4
    geo = FramebufferGeometry(w, h, 32, w * 4, Bitfield(0, 10), Bitfield(10, 10),
                              Bitfield(20, 10), Bitfield(30, 2))
    path = fb_file(geo.size_bytes)
    d = FramebufferDisplay(path, geometry=geo, refresh_hz=500.0)
    assert d.info.bit_depth == 10
    img = _image(h, w, 10)
    d.show(img)
    with pytest.raises(DisplayError, match="uint16"):
        d.show(img.astype(np.uint8))
    d.close()
    words = np.frombuffer(path.read_bytes(), "<u4").reshape(h, w).astype(np.int64)
    for off in (0, 10, 20):
        np.testing.assert_array_equal((words >> off) & 0x3FF, img)
    assert np.all(words >> 30 == 3)


def test_paced_flips_without_vsync_ioctl(fb_file) -> None:
    geo = FramebufferGeometry.standard(4, 2, 32)
    d = FramebufferDisplay(fb_file(geo.size_bytes), geometry=geo, refresh_hz=200.0)
    img = np.zeros((2, 4), np.uint8)
    clock = RealClock()
    flips = [d.show(img) for _ in range(6)]
    now = clock.now()
    assert not d.hardware_vsync  # ioctl fails on a plain file: paced fallback
    steps = np.diff(flips) * 200.0  # on the vsync grid: whole periods (more under load)
    np.testing.assert_allclose(steps, np.rint(steps), atol=1e-6)
    assert np.all(steps >= 1 - 1e-6)
    assert flips[-1] <= now + 1e-6  # show() returns once the flip time has come
    d.close()


def test_wrong_image_and_short_file_are_clear_errors(fb_file) -> None:
    geo = FramebufferGeometry.standard(8, 4, 32)
    with pytest.raises(DisplayError, match="needs 128 B"):
        FramebufferDisplay(fb_file(64), geometry=geo)
    d = FramebufferDisplay(fb_file(geo.size_bytes), geometry=geo, refresh_hz=500.0)
    with pytest.raises(DisplayError, match=r"shape \(3, 8\)"):
        d.show(np.zeros((3, 8), np.uint8))
    d.close()
    with pytest.raises(DisplayError, match="show\\(\\) after close"):
        d.show(np.zeros((4, 8), np.uint8))


def test_plain_file_without_geometry_says_what_to_configure(fb_file) -> None:
    with pytest.raises(DisplayError, match=r"geometry ioctl failed.*rig config"):
        FramebufferDisplay(fb_file(64))
    with pytest.raises(DisplayError, match="cannot open"):
        FramebufferDisplay("/nonexistent/fb9")


def test_geometry_from_sysfs_and_listing(tmp_path: Path, fb_file) -> None:
    sys_fb = tmp_path / "graphics" / "fb0"
    sys_fb.mkdir(parents=True)
    (sys_fb / "virtual_size").write_text("6,3\n")
    (sys_fb / "bits_per_pixel").write_text("32\n")
    (sys_fb / "stride").write_text("32\n")
    (sys_fb / "modes").write_text("U:6x3p-75\n")
    geo = geometry_from_sysfs(sys_fb)
    assert (geo.width, geo.height, geo.bits_per_pixel, geo.line_length) == (6, 3, 32, 32)
    assert geo.refresh_hz == 75.0
    path = fb_file(geo.size_bytes)
    d = FramebufferDisplay(path, sysfs_root=sys_fb)
    assert d.info.refresh_hz == 75.0 and d.info.width_px == 6
    d.close()
    dev = tmp_path / "dev"
    dev.mkdir()
    (dev / "fb0").write_bytes(b"")
    found = list_framebuffers(dev, tmp_path / "graphics")
    assert found[0][0] == str(dev / "fb0") and "6x3 32 bpp" in found[0][2]
    (sys_fb / "bits_per_pixel").unlink()
    with pytest.raises(DisplayError, match="bits_per_pixel"):
        geometry_from_sysfs(sys_fb)


def test_parse_kernel_structs() -> None:
    var = [0] * 40
    var[:7] = [1920, 1080, 1920, 2160, 0, 0, 32]
    var[8:20] = [16, 8, 0, 8, 8, 0, 0, 8, 0, 24, 8, 0]
    var[25:32] = [6734, 148, 88, 36, 4, 44, 5]  # pixclock (ps) and margins of 1080p60
    geo = parse_var_screeninfo(struct.pack("=40I", *var))
    assert (geo.width, geo.height, geo.red, geo.transp) == (1920, 1080, Bitfield(16, 8),
                                                            Bitfield(24, 8))
    assert geo.refresh_hz == pytest.approx(60.0, rel=1e-3)
    fix = struct.pack("@16sLIIIIHHHILIIH", b"simplefb", 0, 8294400, 0, 0, 2, 1, 1, 0, 7680,
                      0, 0, 0, 0)
    assert parse_fix_screeninfo(fix) == ("simplefb", 8294400, 7680)
