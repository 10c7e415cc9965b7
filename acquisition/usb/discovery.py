"""pyusb discovery of USB cameras: UVC (class 0x0E) and USB3 Vision (0xEF/0x05).

Each camera is reported with vendor, product, serial and bus path, and mapped to the
backend that opens it (UVC -> OpenCV/V4L2, USB3 Vision -> Aravis). A pyusb backend can
be injected (tests use a fake `usb.backend.IBackend`); reading descriptors never
claims an interface, so a camera in use elsewhere is still listed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

CLASS_VIDEO = 0x0E  # UVC
CLASS_MISC = 0xEF
SUBCLASS_USB3_VISION = 0x05


@dataclass(frozen=True)
class UsbCamera:
    """A USB camera found on the bus and the phasecal backend that can open it."""

    kind: str  # "uvc" or "usb3vision"
    vendor_id: int
    product_id: int
    vendor: str | None
    product: str | None
    serial: str | None
    bus_path: str  # "bus-port.port...", like /sys/bus/usb/devices
    backend: str  # "opencv" or "aravis"
    open_hint: str


def camera_kind(interfaces: list[tuple[int, int]]) -> str | None:
    """'uvc' / 'usb3vision' from (class, subclass) of a device's interfaces, else None."""
    if any(c == CLASS_VIDEO for c, _ in interfaces):
        return "uvc"
    if any(c == CLASS_MISC and s == SUBCLASS_USB3_VISION for c, s in interfaces):
        return "usb3vision"
    return None


def _string(dev: Any, index: int) -> str | None:
    """A string descriptor, or None when absent or unreadable (permissions, busy)."""
    import usb.core
    import usb.util

    if not index:
        return None
    try:
        return usb.util.get_string(dev, index)
    except (usb.core.USBError, ValueError, NotImplementedError):
        return None


def bus_path(dev: Any) -> str:
    """`bus-port.port` (the sysfs name) of a device."""
    ports = getattr(dev, "port_numbers", None) or ()
    return f"{dev.bus}-{'.'.join(str(p) for p in ports)}" if ports else f"{dev.bus}-0"


def _interfaces(dev: Any) -> list[tuple[int, int]]:
    out = [(dev.bDeviceClass, dev.bDeviceSubClass)]
    for cfg in dev:
        out.extend((i.bInterfaceClass, i.bInterfaceSubClass) for i in cfg)
    return out


def list_usb_cameras(backend: Any = None) -> list[UsbCamera]:
    """All UVC and USB3 Vision cameras visible to pyusb (empty without libusb access)."""
    import usb.core

    try:
        devices = list(usb.core.find(find_all=True, backend=backend))
    except (usb.core.NoBackendError, usb.core.USBError):
        return []
    cams = []
    for dev in devices:
        kind = camera_kind(_interfaces(dev))
        if kind is None:
            continue
        vendor, product = _string(dev, dev.iManufacturer), _string(dev, dev.iProduct)
        serial = _string(dev, dev.iSerialNumber)
        path = bus_path(dev)
        if kind == "uvc":
            hint = f"camera backend 'opencv' with source /dev/videoN of USB device {path}"
            be = "opencv"
        else:
            hint = f"camera backend 'aravis' with device '{vendor}-{product}-{serial}'"
            be = "aravis"
        cams.append(UsbCamera(kind, dev.idVendor, dev.idProduct, vendor, product, serial,
                              path, be, hint))
    return cams
