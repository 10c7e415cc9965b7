"""SDL display: headless drivers in-process, and full-screen under Xvfb with X read-back."""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np
import pytest

from acquisition.clock import RealClock
from acquisition.errors import DisplayError

ROOT = Path(__file__).resolve().parents[2]
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def _pattern(h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return ((xx * 7 + yy * 13) % 256).astype(np.uint8)


@pytest.mark.parametrize("driver", ["dummy", "offscreen"])
def test_headless_driver_exact_pixels_and_paced_flips(driver: str, monkeypatch) -> None:
    import pygame

    from acquisition.display.sdl import SdlDisplay

    monkeypatch.setenv("SDL_VIDEODRIVER", driver)
    d = SdlDisplay(0, size=(40, 24), refresh_hz=120.0, clock=RealClock())
    try:
        img = _pattern(24, 40)
        flips = [d.show(img) for _ in range(5)]
        shown = pygame.surfarray.array3d(pygame.display.get_surface())
        for ch in range(3):
            np.testing.assert_array_equal(shown[:, :, ch].T, img)
        assert not d.vsync_granted  # these drivers cannot sync: flips are paced
        steps = np.diff(flips) * 120.0  # whole refresh periods (more if the host is slow)
        np.testing.assert_allclose(steps, np.rint(steps), atol=1e-6)
        assert np.all(steps >= 1 - 1e-6)
        with pytest.raises(DisplayError, match="uint8"):
            d.show(img.astype(np.uint16))
        with pytest.raises(DisplayError, match="shape"):
            d.show(img[:10])
    finally:
        d.close()


def test_missing_monitor_is_a_clear_error(monkeypatch) -> None:
    from acquisition.display.sdl import SdlDisplay

    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    with pytest.raises(DisplayError, match="monitor 3 does not exist"):
        SdlDisplay(3)


def read_xwd(data: bytes) -> np.ndarray:
    """An XWD (X window dump) ZPixmap of 24/32 bpp -> (H, W, 3) RGB."""
    fields = struct.unpack(">25I", data[:100])
    header_size, _ver, _fmt, _depth, width, height = fields[:6]
    byte_order, bpp, bytes_per_line = fields[7], fields[11], fields[12]
    red_mask, green_mask, blue_mask = fields[14:17]
    ncolors = fields[19]
    start = header_size + 12 * ncolors
    assert bpp == 32, f"expected a 32-bpp dump, got {bpp}"
    rows = np.frombuffer(data[start:start + height * bytes_per_line], np.uint8)
    rows = rows.reshape(height, bytes_per_line)[:, : width * 4]
    words = rows.copy().view(">u4" if byte_order else "<u4").reshape(height, width)

    def channel(mask: int) -> np.ndarray:
        shift = (mask & -mask).bit_length() - 1
        return ((words & mask) >> shift).astype(np.uint8)

    return np.stack([channel(red_mask), channel(green_mask), channel(blue_mask)], axis=2)


CHILD = textwrap.dedent(
    """
    import shutil, sys, numpy as np
    from acquisition.display.sdl import SdlDisplay
    w, h, fb, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
    d = SdlDisplay(0, refresh_hz=60.0)  # full screen at the monitor's native size
    yy, xx = np.mgrid[0:h, 0:w]
    img = ((xx * 7 + yy * 13) % 256).astype(np.uint8)
    d.show(img)
    d.show(img)  # a second flip: the X server has surely composed the first
    shutil.copyfile(fb, out)  # Xvfb's screen memory, an XWD file (-fbdir)
    print(d.info.name, d.info.width_px, d.info.height_px)
    d.close()
    """
)


@pytest.fixture
def xvfb():
    """An Xvfb server on a free display number (-displayfd) whose screen memory is an XWD
    file (-fbdir): (display, screen file). Stopped afterwards."""
    if shutil.which("Xvfb") is None:
        if IN_CI:
            pytest.fail("Xvfb missing: run scripts/install-system-deps.sh (Debian xvfb)")
        pytest.skip("Xvfb not installed (scripts/install-system-deps.sh installs it)")
    fbdir = Path(tempfile.mkdtemp(prefix="phasecal-xvfb-"))
    r, w = os.pipe()
    proc = subprocess.Popen(["Xvfb", "-displayfd", str(w), "-screen", "0", "320x200x24",
                             "-fbdir", str(fbdir), "-nolisten", "tcp"], pass_fds=(w,),
                            stderr=subprocess.DEVNULL)
    os.close(w)
    try:
        with os.fdopen(r) as f:
            number = f.readline().strip()
        assert number.isdigit(), "Xvfb did not report a display number"
        yield f":{number}", fbdir / "Xvfb_screen0"
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        shutil.rmtree(fbdir, ignore_errors=True)


def test_fullscreen_under_xvfb_reads_back_exactly(xvfb, tmp_path: Path) -> None:
    display, screen_file = xvfb
    env = {**os.environ, "DISPLAY": display, "SDL_VIDEODRIVER": "x11",
           "PYTHONPATH": str(ROOT)}
    dump = tmp_path / "screen.xwd"
    res = subprocess.run([sys.executable, "-c", CHILD, "320", "200", str(screen_file),
                          str(dump)], env=env,
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    assert "x11" in res.stdout and "320 200" in res.stdout
    rgb = read_xwd(dump.read_bytes())
    want = _pattern(200, 320)
    assert rgb.shape == (200, 320, 3)
    for ch in range(3):
        np.testing.assert_array_equal(rgb[:, :, ch], want)
