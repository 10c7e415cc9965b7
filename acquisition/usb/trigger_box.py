"""Optional USB trigger box: one vendor control transfer per display flip.

The box turns each transfer into an electrical pulse on the camera's trigger line, so a
hardware-triggered camera exposes in step with the screen. The request carries a 16-bit
flip counter in wValue, letting the box (and its log) detect missed flips.
"""

from __future__ import annotations

from typing import Any, Protocol

from acquisition.errors import AcquisitionError

VENDOR_OUT = 0x40  # bmRequestType: vendor, host-to-device, device recipient


class TriggerSink(Protocol):
    """Something the controller calls right after each display flip."""

    def fire(self) -> None: ...

    def close(self) -> None: ...


class TriggerBoxError(AcquisitionError):
    """The trigger box is missing, unplugged or refused a request."""


class UsbTriggerBox:
    """A trigger box on USB found by vendor/product id (and serial when several)."""

    def __init__(
        self,
        vendor_id: int,
        product_id: int,
        *,
        serial: str | None = None,
        request: int = 0x01,
        index: int = 0,
        timeout_ms: int = 100,
        backend: Any = None,
    ) -> None:
        import usb.core
        import usb.util

        self._usb = usb
        self.request, self.index, self.timeout_ms = request, index, timeout_ms
        self.count = 0
        where = f"trigger box {vendor_id:04x}:{product_id:04x}"
        devices = list(usb.core.find(find_all=True, idVendor=vendor_id, idProduct=product_id,
                                     backend=backend) or [])
        if serial is not None:
            devices = [d for d in devices if _serial(d) == serial]
            where += f" serial {serial}"
        if not devices:
            raise TriggerBoxError(f"{where}: not found on USB (plugged in? udev permissions?)")
        if len(devices) > 1:
            raise TriggerBoxError(f"{where}: {len(devices)} boxes found; set trigger_box.serial")
        self._dev = devices[0]
        self.name = where

    def fire(self) -> None:
        """Send one trigger request; raises TriggerBoxError when the box does not take it."""
        try:
            self._dev.ctrl_transfer(VENDOR_OUT, self.request, self.count & 0xFFFF, self.index,
                                    b"", self.timeout_ms)
        except self._usb.core.USBError as exc:
            raise TriggerBoxError(f"{self.name}: trigger {self.count} failed ({exc})") from exc
        self.count += 1

    def close(self) -> None:
        self._usb.util.dispose_resources(self._dev)


def _serial(dev: Any) -> str | None:
    import usb.core
    import usb.util

    try:
        return usb.util.get_string(dev, dev.iSerialNumber) if dev.iSerialNumber else None
    except (usb.core.USBError, ValueError):
        return None
