"""Linux framebuffer display (`/dev/fbN`): ioctl or injected geometry, mmap writes, vsync.

Geometry comes from `FBIOGET_VSCREENINFO`/`FBIOGET_FSCREENINFO` on a real device, from a
sysfs-like folder (`/sys/class/graphics/fbN`), or from the rig config; the same mmap
path then writes every pixel format (16/24/32 bpp, any channel offsets, any stride), so
it is tested on a plain file. Flips wait on `FBIO_WAITFORVSYNC` where the driver has it
and are paced on the refresh period where it does not.
"""

from __future__ import annotations

import fcntl
import mmap
import os
import struct
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from acquisition.clock import Clock, RealClock
from acquisition.display.vsync import VsyncPacer
from acquisition.errors import DisplayError
from acquisition.protocols import DisplayInfo

FBIOGET_VSCREENINFO = 0x4600
FBIOGET_FSCREENINFO = 0x4602
FBIO_WAITFORVSYNC = 0x40044620  # _IOW('F', 0x20, __u32)

# struct fb_var_screeninfo: 40 x __u32 (160 bytes).
_VAR = struct.Struct("=40I")
# struct fb_fix_screeninfo on LP64: id[16], smem_start, smem_len, type, type_aux, visual,
# xpanstep, ypanstep, ywrapstep, line_length, mmio_start, mmio_len, accel, capabilities.
_FIX = struct.Struct("@16sLIIIIHHHILIIH")
_FIX_SIZE = 80


@dataclass(frozen=True)
class Bitfield:
    """Where one colour channel sits in a pixel word (bit offset, bit length)."""

    offset: int
    length: int


@dataclass(frozen=True)
class FramebufferGeometry:
    """Visible resolution, pixel layout and memory stride of a framebuffer."""

    width: int
    height: int
    bits_per_pixel: int
    line_length: int  # bytes per row in memory (>= width * bytes per pixel)
    red: Bitfield
    green: Bitfield
    blue: Bitfield
    transp: Bitfield = Bitfield(0, 0)
    refresh_hz: float | None = None

    def __post_init__(self) -> None:
        if self.bits_per_pixel not in (16, 24, 32):
            raise DisplayError(
                f"framebuffer bits_per_pixel: expected 16, 24 or 32, got {self.bits_per_pixel}"
            )
        if self.width <= 0 or self.height <= 0:
            raise DisplayError(f"framebuffer size must be positive, got {self.width}x{self.height}")
        if self.line_length < self.width * self.bytes_per_pixel:
            raise DisplayError(
                f"framebuffer line_length {self.line_length} B is shorter than a row "
                f"({self.width} px x {self.bytes_per_pixel} B)"
            )
        for name in ("red", "green", "blue", "transp"):
            f: Bitfield = getattr(self, name)
            if f.offset < 0 or f.length < 0 or f.offset + f.length > self.bits_per_pixel:
                raise DisplayError(f"framebuffer {name} bitfield {f} does not fit in a pixel")

    @property
    def bytes_per_pixel(self) -> int:
        """Bytes per pixel in memory."""
        return self.bits_per_pixel // 8

    @property
    def size_bytes(self) -> int:
        """Bytes the visible image occupies (rows x stride)."""
        return self.height * self.line_length

    @property
    def channel_bits(self) -> int:
        """Smallest colour channel depth: what a grey code can be shown with."""
        return min(self.red.length, self.green.length, self.blue.length)

    @classmethod
    def standard(
        cls, width: int, height: int, bits_per_pixel: int = 32,
        line_length: int | None = None, refresh_hz: float | None = None,
    ) -> FramebufferGeometry:
        """Common layouts: XRGB8888 (32), RGB888 (24), RGB565 (16)."""
        if bits_per_pixel == 16:
            r, g, b = Bitfield(11, 5), Bitfield(5, 6), Bitfield(0, 5)
        else:
            r, g, b = Bitfield(16, 8), Bitfield(8, 8), Bitfield(0, 8)
        stride = line_length if line_length is not None else width * bits_per_pixel // 8
        return cls(width, height, bits_per_pixel, stride, r, g, b, refresh_hz=refresh_hz)


def parse_var_screeninfo(buf: bytes) -> FramebufferGeometry:
    """Geometry from a raw `fb_var_screeninfo` (line length = xres_virtual * bpp / 8)."""
    v = _VAR.unpack(buf[: _VAR.size])
    xres, yres, xres_virtual, _yv, _xo, _yo, bpp = v[:7]
    red, green, blue, transp = (Bitfield(v[8 + 3 * i], v[9 + 3 * i]) for i in range(4))
    pixclock = v[25]
    left, right, upper, lower, hsync, vsync = v[26:32]
    refresh = None
    total = (xres + left + right + hsync) * (yres + upper + lower + vsync)
    if pixclock and total:
        refresh = 1e12 / (pixclock * total)
    return FramebufferGeometry(
        xres, yres, bpp, xres_virtual * bpp // 8, red, green, blue, transp, refresh
    )


def parse_fix_screeninfo(buf: bytes) -> tuple[str, int, int]:
    """(driver id, smem_len, line_length) from a raw `fb_fix_screeninfo`."""
    f = _FIX.unpack(buf[: _FIX.size])
    return f[0].split(b"\0", 1)[0].decode(errors="replace"), f[2], f[9]


def geometry_from_ioctl(fd: int) -> tuple[FramebufferGeometry, str]:
    """Query a framebuffer device; raises OSError where the file is not a framebuffer."""
    var = bytearray(_VAR.size)
    fcntl.ioctl(fd, FBIOGET_VSCREENINFO, var, True)
    fix = bytearray(_FIX_SIZE)
    fcntl.ioctl(fd, FBIOGET_FSCREENINFO, fix, True)
    ident, _smem, line_length = parse_fix_screeninfo(bytes(fix))
    geo = parse_var_screeninfo(bytes(var))
    return replace(geo, line_length=line_length or geo.line_length), ident


def geometry_from_sysfs(root: str | Path) -> FramebufferGeometry:
    """Geometry from a sysfs folder like `/sys/class/graphics/fb0` (standard channel layout).

    Reads `virtual_size` ("W,H"), `bits_per_pixel`, `stride` and, when present, the
    refresh rate of the first entry of `modes` (e.g. "U:1920x1080p-60").
    """
    root = Path(root)

    def read(name: str) -> str:
        path = root / name
        try:
            return path.read_text().strip()
        except OSError as exc:
            raise DisplayError(f"framebuffer sysfs: cannot read {path}: {exc.strerror}") from exc

    try:
        w, h = (int(s) for s in read("virtual_size").split(","))
        bpp = int(read("bits_per_pixel"))
        stride = int(read("stride")) if (root / "stride").exists() else None
    except ValueError as exc:
        raise DisplayError(f"framebuffer sysfs {root}: malformed value ({exc})") from exc
    refresh = None
    if (root / "modes").exists():
        first = (root / "modes").read_text().split("\n", 1)[0]
        if "-" in first:
            try:
                refresh = float(first.rsplit("-", 1)[1])
            except ValueError:
                refresh = None
    return FramebufferGeometry.standard(w, h, bpp, stride, refresh)


def _channel_lut(field: Bitfield, depth: int) -> np.ndarray:
    """Grey code (0..2^depth-1) -> this channel's bits, already shifted into place."""
    codes = np.arange(1 << depth, dtype=np.float64)
    top = (1 << field.length) - 1
    scaled = np.rint(codes * top / ((1 << depth) - 1)).astype(np.uint32)
    return scaled << np.uint32(field.offset)


def pixel_lut(geo: FramebufferGeometry, depth: int) -> np.ndarray:
    """Grey code -> packed pixel word (uint32), alpha fully opaque where present."""
    word = _channel_lut(geo.red, depth) | _channel_lut(geo.green, depth)
    word |= _channel_lut(geo.blue, depth)
    if geo.transp.length:
        word |= np.uint32(((1 << geo.transp.length) - 1) << geo.transp.offset)
    return word


def encode_rows(image: np.ndarray, geo: FramebufferGeometry, lut: np.ndarray) -> np.ndarray:
    """Grey image -> (H, W * bytes_per_pixel) uint8 rows in the framebuffer's byte order."""
    words = lut[image]
    bpp = geo.bytes_per_pixel
    if bpp == 4:
        return words.astype("<u4").view(np.uint8).reshape(geo.height, -1)
    if bpp == 2:
        return words.astype("<u2").view(np.uint8).reshape(geo.height, -1)
    as_bytes = words.astype("<u4").view(np.uint8).reshape(geo.height, geo.width, 4)
    return as_bytes[:, :, :3].reshape(geo.height, -1)


class FramebufferDisplay:
    """A `Display` on a Linux framebuffer device (or a file laid out like one)."""

    def __init__(
        self,
        path: str | Path = "/dev/fb0",
        *,
        geometry: FramebufferGeometry | None = None,
        sysfs_root: str | Path | None = None,
        refresh_hz: float | None = None,
        clock: Clock | None = None,
        name: str | None = None,
    ) -> None:
        self._path = Path(path)
        self._clock = clock if clock is not None else RealClock()
        try:
            self._fd = os.open(self._path, os.O_RDWR)
        except OSError as exc:
            raise DisplayError(
                f"framebuffer {self._path}: cannot open ({exc.strerror}); check the device "
                "exists and you are in the 'video' group"
            ) from exc
        try:
            ident = "file"
            if geometry is None and sysfs_root is not None:
                geometry = geometry_from_sysfs(sysfs_root)
            if geometry is None:
                try:
                    geometry, ident = geometry_from_ioctl(self._fd)
                except OSError as exc:
                    raise DisplayError(
                        f"framebuffer {self._path}: geometry ioctl failed ({exc.strerror}); "
                        "not a framebuffer device: give the geometry in the rig config "
                        "([display] width/height/bits_per_pixel) or a sysfs_root"
                    ) from exc
            self.geometry = geometry
            size = os.fstat(self._fd).st_size
            if self._path.is_file() and size < geometry.size_bytes:
                raise DisplayError(
                    f"framebuffer file {self._path} has {size} B, the geometry needs "
                    f"{geometry.size_bytes} B ({geometry.height} rows x {geometry.line_length} B)"
                )
            self._map = mmap.mmap(self._fd, geometry.size_bytes, mmap.MAP_SHARED,
                                  mmap.PROT_READ | mmap.PROT_WRITE)
        except BaseException:
            os.close(self._fd)
            raise
        self._rows = np.ndarray((geometry.height, geometry.line_length), np.uint8, self._map)
        self._visible = self._rows[:, : geometry.width * geometry.bytes_per_pixel]
        self._depth = 10 if geometry.channel_bits >= 10 else 8
        self._lut = pixel_lut(geometry, self._depth)
        rate = refresh_hz or geometry.refresh_hz or 60.0
        self._pacer = VsyncPacer(self._clock, 1.0 / rate, self._wait_vsync)
        self._info = DisplayInfo(
            name or f"framebuffer {self._path} ({ident})",
            geometry.width, geometry.height, rate, self._depth,
        )
        self._closed = False

    def _wait_vsync(self) -> bool:
        """Block in FBIO_WAITFORVSYNC; False where the driver (or a plain file) lacks it."""
        try:
            fcntl.ioctl(self._fd, FBIO_WAITFORVSYNC, struct.pack("I", 0))
        except OSError:
            return False
        return True

    @property
    def info(self) -> DisplayInfo:
        return self._info

    @property
    def hardware_vsync(self) -> bool:
        """Whether flips are timed by the driver's vsync (else paced on the period)."""
        return self._pacer.hardware

    def show(self, image: np.ndarray) -> float:
        """Write the image into the framebuffer, then return the next vsync time."""
        if self._closed:
            raise DisplayError(f"framebuffer {self._path}: show() after close()")
        g = self.geometry
        img = np.asarray(image)
        if img.shape != (g.height, g.width):
            raise DisplayError(
                f"framebuffer {self._path}: image shape {img.shape} != screen "
                f"({g.height}, {g.width})"
            )
        want = np.uint8 if self._depth == 8 else np.uint16
        if img.dtype != want:
            raise DisplayError(
                f"framebuffer {self._path}: expected {np.dtype(want).name} codes for a "
                f"{self._depth}-bit display, got {img.dtype}"
            )
        if self._depth == 10 and int(img.max(initial=0)) > 1023:
            raise DisplayError(f"framebuffer {self._path}: 10-bit codes must be <= 1023")
        self._visible[:] = encode_rows(img, g, self._lut)
        return self._pacer.next_flip()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        del self._visible, self._rows
        self._map.close()
        os.close(self._fd)


def list_framebuffers(dev_root: str | Path = "/dev", sysfs: str | Path = "/sys/class/graphics"):
    """Framebuffer devices present: [(device path, geometry or None, note)]."""
    found = []
    for dev in sorted(Path(dev_root).glob("fb[0-9]*")):
        root = Path(sysfs) / dev.name
        try:
            geo = geometry_from_sysfs(root)
            found.append((str(dev), geo, f"{geo.width}x{geo.height} {geo.bits_per_pixel} bpp"))
        except DisplayError as exc:
            found.append((str(dev), None, str(exc)))
    return found
