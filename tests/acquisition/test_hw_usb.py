"""USB discovery and trigger box through pyusb with a fake `usb.backend.IBackend`."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import usb.backend
import usb.core

from acquisition.usb.discovery import list_usb_cameras
from acquisition.usb.trigger_box import VENDOR_OUT, TriggerBoxError, UsbTriggerBox


def _device(vid, pid, strings, interfaces, bus=1, ports=(2,), dev_class=0, dev_sub=0):
    """A fake device: descriptors as pyusb's backends return them."""
    return SimpleNamespace(
        desc=SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0300, bDeviceClass=dev_class,
            bDeviceSubClass=dev_sub, bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=vid,
            idProduct=pid, bcdDevice=0x0100, iManufacturer=1 if strings[0] else 0,
            iProduct=2 if strings[1] else 0, iSerialNumber=3 if strings[2] else 0,
            bNumConfigurations=1, address=len(ports) + 3, bus=bus, port_number=ports[-1],
            port_numbers=ports, speed=4),
        strings=strings,
        interfaces=[
            SimpleNamespace(bLength=9, bDescriptorType=4, bInterfaceNumber=i,
                            bAlternateSetting=0, bNumEndpoints=0, bInterfaceClass=c,
                            bInterfaceSubClass=s, bInterfaceProtocol=0, iInterface=0,
                            extra_descriptors=[])
            for i, (c, s) in enumerate(interfaces)
        ],
        transfers=[],
        unplugged=False,
    )


class FakeBackend(usb.backend.IBackend):
    """Enumerates the given devices; answers string descriptors; logs control transfers."""

    def __init__(self, devices) -> None:
        self.devices = devices

    def enumerate_devices(self):
        yield from self.devices

    def get_device_descriptor(self, dev):
        return dev.desc

    def get_configuration_descriptor(self, dev, config):
        return SimpleNamespace(bLength=9, bDescriptorType=2, wTotalLength=9,
                               bNumInterfaces=len(dev.interfaces), bConfigurationValue=1,
                               iConfiguration=0, bmAttributes=0x80, bMaxPower=250,
                               extra_descriptors=[])

    def get_interface_descriptor(self, dev, intf, alt, config):
        if alt != 0:
            raise IndexError("one alternate setting per interface")  # ends pyusb's scan
        return dev.interfaces[intf]

    def open_device(self, dev):
        return dev

    def close_device(self, handle):
        pass

    def get_configuration(self, handle):
        return 1

    def ctrl_transfer(self, handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        if handle.unplugged:
            raise usb.core.USBError("No such device", errno=19)
        if bmRequestType & 0x80 and bRequest == 6 and wValue >> 8 == 3:  # GET_DESCRIPTOR
            index = wValue & 0xFF
            payload = (b"\x09\x04" if index == 0
                       else handle.strings[index - 1].encode("utf-16-le"))
            desc = bytes([2 + len(payload), 3]) + payload
            n = min(len(data), len(desc))
            data[:n] = type(data)("B", desc[:n])
            return n
        handle.transfers.append((bmRequestType, bRequest, wValue, wIndex, bytes(data)))
        return len(data)


def test_finds_uvc_and_usb3vision_cameras_only() -> None:
    devices = [
        _device(0x046D, 0x085E, ("Logitech", "BRIO", "AB12"), [(0x0E, 1), (0x0E, 2), (1, 1)],
                bus=2, ports=(1, 4), dev_class=0xEF, dev_sub=2),
        _device(0x2676, 0xBA02, ("Basler", "acA1920-155um", "2233"), [(0xEF, 0x05)],
                bus=3, ports=(2,)),
        _device(0x0781, 0x5583, ("SanDisk", "Ultra", "X"), [(0x08, 6)]),  # a USB stick
        _device(0x1234, 0x0001, (None, None, None), [(0x0E, 1)], bus=1, ports=(3, 1, 2)),
    ]
    cams = list_usb_cameras(FakeBackend(devices))
    assert [(c.kind, c.backend, c.bus_path) for c in cams] == [
        ("uvc", "opencv", "2-1.4"), ("usb3vision", "aravis", "3-2"), ("uvc", "opencv", "1-3.1.2")]
    brio, basler, anon = cams
    assert (brio.vendor, brio.product, brio.serial) == ("Logitech", "BRIO", "AB12")
    assert (basler.vendor_id, basler.product_id) == (0x2676, 0xBA02)
    assert "Basler-acA1920-155um-2233" in basler.open_hint
    assert (anon.vendor, anon.serial) == (None, None)


def test_trigger_box_sends_a_counted_vendor_request_per_fire() -> None:
    box_dev = _device(0x16C0, 0x05DC, ("lab", "flipbox", "S1"), [(0xFF, 0)])
    backend = FakeBackend([box_dev])
    box = UsbTriggerBox(0x16C0, 0x05DC, request=0x21, index=3, backend=backend)
    for _ in range(3):
        box.fire()
    assert box_dev.transfers == [(VENDOR_OUT, 0x21, k, 3, b"") for k in range(3)]
    box_dev.unplugged = True
    with pytest.raises(TriggerBoxError, match="trigger 3 failed"):
        box.fire()
    box.close()


def test_trigger_box_selection_errors() -> None:
    a = _device(0x16C0, 0x05DC, ("lab", "flipbox", "S1"), [(0xFF, 0)])
    b = _device(0x16C0, 0x05DC, ("lab", "flipbox", "S2"), [(0xFF, 0)], ports=(5,))
    backend = FakeBackend([a, b])
    with pytest.raises(TriggerBoxError, match=r"2 boxes found; set trigger_box\.serial"):
        UsbTriggerBox(0x16C0, 0x05DC, backend=backend)
    box = UsbTriggerBox(0x16C0, 0x05DC, serial="S2", backend=backend)
    box.fire()
    assert len(b.transfers) == 1 and not a.transfers
    with pytest.raises(TriggerBoxError, match="not found on USB"):
        UsbTriggerBox(0x16C0, 0x9999, backend=backend)
