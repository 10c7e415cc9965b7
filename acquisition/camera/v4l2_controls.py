"""V4L2 camera controls through `VIDIOC_S_CTRL`/`VIDIOC_G_CTRL` on `/dev/videoN`.

OpenCV's V4L2 backend maps exposure but not auto-gain, and its auto-exposure values are
driver-specific; setting the controls directly makes "auto off, then set, then read
back" explicit. The ioctl function is injectable so the logic is tested without a device.
"""

from __future__ import annotations

import fcntl
import os
import struct
from collections.abc import Callable

from acquisition.errors import CameraError, DeviceSettingsError

VIDIOC_G_CTRL = 0xC008561B  # _IOWR('V', 27, struct v4l2_control)
VIDIOC_S_CTRL = 0xC008561C  # _IOWR('V', 28, struct v4l2_control)

CID_AUTOGAIN = 0x00980912
CID_GAIN = 0x00980913
CID_EXPOSURE_AUTO = 0x009A0901
CID_EXPOSURE_ABSOLUTE = 0x009A0902  # units of 100 us
CID_EXPOSURE_AUTO_PRIORITY = 0x009A0903
EXPOSURE_MANUAL = 1

IoctlFn = Callable[[int, int, bytearray], object]
_CTRL = struct.Struct("=Ii")


class V4l2Controls:
    """Reads and writes V4L2 controls of one device file."""

    def __init__(self, path: str, ioctl: IoctlFn | None = None, fd: int | None = None) -> None:
        self.path = path
        self._ioctl = ioctl if ioctl is not None else (lambda f, r, b: fcntl.ioctl(f, r, b, True))
        self._own_fd = fd is None
        if fd is None:
            try:
                fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)
            except OSError as exc:
                raise CameraError(
                    f"V4L2 {path}: cannot open for controls ({exc.strerror})"
                ) from exc
        self._fd = fd

    def get(self, cid: int) -> int:
        """Current value of a control."""
        buf = bytearray(_CTRL.pack(cid, 0))
        try:
            self._ioctl(self._fd, VIDIOC_G_CTRL, buf)
        except OSError as exc:
            raise DeviceSettingsError(
                f"V4L2 {self.path}: control {cid:#x} not readable ({exc.strerror})"
            ) from exc
        return _CTRL.unpack(buf)[1]

    def set(self, cid: int, value: int) -> int:
        """Set a control and return the value the driver reports back."""
        buf = bytearray(_CTRL.pack(cid, int(value)))
        try:
            self._ioctl(self._fd, VIDIOC_S_CTRL, buf)
        except OSError as exc:
            raise DeviceSettingsError(
                f"V4L2 {self.path}: cannot set control {cid:#x} to {value} ({exc.strerror})"
            ) from exc
        return self.get(cid)

    def set_manual_exposure(self, exposure_s: float) -> float:
        """Auto exposure off (and no frame-rate priority), then exposure; returns read-back s."""
        self.set(CID_EXPOSURE_AUTO, EXPOSURE_MANUAL)
        try:
            self.set(CID_EXPOSURE_AUTO_PRIORITY, 0)
        except DeviceSettingsError:
            pass  # many drivers lack this control; manual exposure alone is enough there
        units = max(1, round(exposure_s / 100e-6))
        got = self.set(CID_EXPOSURE_ABSOLUTE, units)
        return got * 100e-6

    def set_manual_gain(self, raw_gain: int | None) -> int | None:
        """Auto gain off, then the raw gain (None keeps the current one); returns read-back."""
        try:
            self.set(CID_AUTOGAIN, 0)
        except DeviceSettingsError:
            pass  # no auto-gain control: the gain is already manual
        if raw_gain is None:
            return self.get(CID_GAIN)
        return self.set(CID_GAIN, raw_gain)

    def close(self) -> None:
        if self._own_fd:
            os.close(self._fd)
