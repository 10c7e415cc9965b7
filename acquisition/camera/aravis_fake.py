"""Aravis' GigE Vision fake camera on loopback, showing images chosen from Python.

`Aravis.GvFakeCamera` serves a real GigE Vision device (GVCP control, GVSP stream) that
the normal Aravis client stack opens by address. Its images come from a fill-pattern
callback; passing a Python callable through introspection crashes (the closure is freed
at once), so the callback is installed through ctypes into libaravis with a C function
pointer this object keeps alive. The fake then delivers whatever `source` renders,
through the whole Aravis stack (tests, and rigs that run a simulated scene on real
drivers). Only 127.0.0.1 is used and device discovery is never called.
"""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import tempfile
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquisition.camera.aravis_gi import GLib, aravis, libaravis
from acquisition.camera.pixel_formats import pixel_format
from acquisition.errors import CameraError

# Only one fake can serve 127.0.0.1 (GVCP port 3956): processes take this lock first.
LOCK_PATH = Path(tempfile.gettempdir()) / "phasecal-aravis-fake.lock"

FILL_PATTERN = ctypes.CFUNCTYPE(
    None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32
)


@dataclass(frozen=True)
class FillRequest:
    """What the fake camera asks for: image size, exposure, raw gain, pixel format."""

    width: int
    height: int
    exposure_us: int
    gain: int
    pixel_format: str


FrameSource = Callable[[FillRequest], np.ndarray]


def gobject_pointer(obj: object) -> int:
    """The C address of a PyGObject instance (from its `__gpointer__` capsule)."""
    get = ctypes.pythonapi.PyCapsule_GetPointer
    get.restype = ctypes.c_void_p
    get.argtypes = [ctypes.py_object, ctypes.c_char_p]
    return int(get(obj.__gpointer__, None))  # type: ignore[attr-defined]


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    lib.arv_fake_camera_set_fill_pattern.argtypes = [ctypes.c_void_p, FILL_PATTERN,
                                                     ctypes.c_void_p]
    lib.arv_fake_camera_set_fill_pattern.restype = None
    lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
    lib.arv_buffer_get_data.restype = ctypes.c_void_p
    for fn in ("arv_buffer_get_image_width", "arv_buffer_get_image_height"):
        getattr(lib, fn).argtypes = [ctypes.c_void_p]
        getattr(lib, fn).restype = ctypes.c_int
    return lib


@contextlib.contextmanager
def fake_camera_lock() -> Iterator[None]:
    """Exclusive, machine-wide right to run a GigE Vision fake on 127.0.0.1 (blocks)."""
    with open(LOCK_PATH, "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


class FakeGigECamera:
    """A GigE Vision fake camera on 127.0.0.1 whose frames come from `source`."""

    def __init__(self, serial: str = "PHASECAL-FAKE", source: FrameSource | None = None,
                 address: str = "127.0.0.1") -> None:
        if address != "127.0.0.1":
            raise CameraError(f"Aravis fake camera: only 127.0.0.1 is allowed, got {address}")
        Aravis = aravis()
        self._lib = _bind(libaravis())
        self.serial = serial
        self.address = address
        self._source = source
        self._lock = threading.Lock()
        self.frames_served = 0
        self.last_error: str | None = None
        try:
            self._gv = Aravis.GvFakeCamera.new(address, serial)
        except GLib.Error as exc:
            raise CameraError(f"Aravis fake camera on {address}: cannot start ({exc})") from exc
        if not self._gv.is_running():
            raise CameraError(
                f"Aravis fake camera on {address}: not running (GVCP port 3956 already in use?)"
            )
        self._fake = self._gv.get_fake_camera()
        self._callback = FILL_PATTERN(self._fill)  # kept alive as long as self
        self._lib.arv_fake_camera_set_fill_pattern(gobject_pointer(self._fake), self._callback,
                                                   None)

    def set_source(self, source: FrameSource | None) -> None:
        """Change what the camera shows (None: a mid-grey frame)."""
        with self._lock:
            self._source = source

    def _fill(self, buf: int, _data: int, exposure_us: int, gain: int, pf_code: int) -> None:
        """C callback (fake camera thread): write the source's image into the buffer."""
        try:
            lib = self._lib
            w, h = lib.arv_buffer_get_image_width(buf), lib.arv_buffer_get_image_height(buf)
            fmt = pixel_format(int(pf_code))
            ptr = lib.arv_buffer_get_data(buf, ctypes.byref(ctypes.c_size_t()))
            nbytes = w * h * fmt.bits_per_pixel // 8
            out = np.ctypeslib.as_array((ctypes.c_uint8 * nbytes).from_address(ptr))
            with self._lock:
                source = self._source
            req = FillRequest(w, h, int(exposure_us), int(gain), fmt.name)
            img = source(req) if source is not None else np.full((h, w), 128, np.uint8)
            out[:] = encode_for_fake(np.asarray(img), fmt.name, w, h)
            self.frames_served += 1
        except Exception as exc:  # an exception must never unwind into C
            self.last_error = f"{type(exc).__name__}: {exc}"

    def stop(self) -> None:
        """Stop serving (the camera disappears from the network, like an unplug)."""
        # Dropping the last references finalizes the GvFakeCamera, which joins its thread
        # and closes its sockets; the C callback object stays alive with `self`.
        self._gv = None
        self._fake = None

    def __enter__(self) -> FakeGigECamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def encode_for_fake(img: np.ndarray, fmt_name: str, width: int, height: int) -> np.ndarray:
    """A grey image -> the raw bytes of a Mono8/Mono16/Bayer8 buffer (grey scene mosaic)."""
    if img.shape != (height, width):
        raise CameraError(f"fake camera source gave {img.shape}, the camera wants "
                          f"({height}, {width})")
    fmt = pixel_format(fmt_name)
    if fmt.bits_per_pixel == 8 and fmt.layout == "mono":
        if img.dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        return img.astype(np.uint8).reshape(-1)
    if fmt.bits_per_pixel == 16 and fmt.layout == "mono":
        if img.dtype == np.uint8:
            img = img.astype(np.uint16) << 8
        return img.astype("<u2").view(np.uint8).reshape(-1)
    raise CameraError(f"fake camera: cannot encode pixel format {fmt_name}")
