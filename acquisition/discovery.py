"""Device listing for `phasecal devices` and `GET /devices`: what a rig config could use.

Listed: the simulated rig, framebuffers (`/dev/fbN`), SDL monitors, V4L2 devices
(`/dev/videoN`, for OpenCV), USB cameras (pyusb) and, only when asked, Aravis devices:
Aravis discovery broadcasts on every network interface, so it is opt-in; a known
address can be probed instead without any broadcast. Nothing here opens a device
for capture. Each entry carries the rig config section that would select it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

VIRTUAL_SDL = ("offscreen", "dummy")


@dataclass(frozen=True)
class DeviceEntry:
    """One device found: what it is, which backend opens it, and its rig config section."""

    kind: str  # "rig", "display", "camera"
    backend: str  # "simulated", "framebuffer", "sdl", "opencv", "aravis", "usb"
    id: str
    description: str
    config: dict[str, Any] = field(default_factory=dict)


def _framebuffers(dev_root: Path, sysfs: Path) -> list[DeviceEntry]:
    from acquisition.display.framebuffer import list_framebuffers

    return [
        DeviceEntry("display", "framebuffer", path, note,
                    {"backend": "framebuffer", "device": path})
        for path, _geo, note in list_framebuffers(dev_root, sysfs)
    ]


def _sdl() -> list[DeviceEntry]:
    from acquisition.display.sdl import list_monitors

    return [
        DeviceEntry("display", "sdl", f"monitor {i}",
                    f"{w}x{h} ({driver} driver"
                    + (", virtual: no real screen)" if driver in VIRTUAL_SDL else ")"),
                    {"backend": "sdl", "monitor": i})
        for i, w, h, driver in list_monitors()
    ]


def _v4l2(dev_root: Path, sysfs: Path) -> list[DeviceEntry]:
    out = []
    for dev in sorted(dev_root.glob("video[0-9]*")):
        name_file = sysfs / dev.name / "name"
        name = name_file.read_text().strip() if name_file.exists() else "V4L2 device"
        out.append(DeviceEntry("camera", "opencv", str(dev), name,
                               {"backend": "opencv", "source": str(dev)}))
    return out


def list_device_nodes(dev_root: str | Path = "/dev",
                      sysfs_root: str | Path = "/sys/class") -> list[DeviceEntry]:
    """The framebuffers and V4L2 devices under `dev_root`: the devices a rig config names by
    their path, which is what a REST client may name (`api.rig_policy`) without any
    broadcast or driver query."""
    dev, sysfs = Path(dev_root), Path(sysfs_root)
    return _framebuffers(dev, sysfs / "graphics") + _v4l2(dev, sysfs / "video4linux")


def _usb(backend: Any) -> list[DeviceEntry]:
    from acquisition.usb.discovery import list_usb_cameras

    return [
        DeviceEntry("camera", c.backend, f"usb {c.bus_path}",
                    f"{c.kind} {c.vendor_id:04x}:{c.product_id:04x} {c.vendor or '?'} "
                    f"{c.product or '?'} serial {c.serial or '?'}; {c.open_hint}",
                    {"backend": c.backend})
        for c in list_usb_cameras(backend)
    ]


def _aravis_entry(Aravis: Any, device: str) -> DeviceEntry:
    cam = Aravis.Camera.new(device)
    desc = (f"{cam.get_vendor_name()} {cam.get_model_name()} serial "
            f"{cam.get_device_serial_number()}")
    return DeviceEntry("camera", "aravis", device, desc, {"backend": "aravis", "device": device})


def _aravis(discover: bool, addresses: list[str]) -> list[DeviceEntry]:
    from acquisition.camera.aravis_gi import GLib, aravis

    Aravis = aravis()
    out = []
    for address in addresses:
        try:
            out.append(_aravis_entry(Aravis, address))
        except GLib.Error as exc:
            out.append(DeviceEntry("camera", "aravis", address, f"not answering: {exc.message}"))
    if discover:
        Aravis.update_device_list()  # broadcasts: only on explicit request
        for i in range(Aravis.get_n_devices()):
            dev_id = Aravis.get_device_id(i)
            desc = (f"{Aravis.get_device_vendor(i)} {Aravis.get_device_model(i)} at "
                    f"{Aravis.get_device_address(i)} ({Aravis.get_device_protocol(i)})")
            out.append(DeviceEntry("camera", "aravis", dev_id, desc,
                                   {"backend": "aravis", "device": dev_id}))
    return out


def list_devices(
    *,
    aravis_discovery: bool = False,
    aravis_addresses: list[str] | None = None,
    usb_backend: Any = None,
    dev_root: str | Path = "/dev",
    sysfs_root: str | Path = "/sys/class",
) -> list[DeviceEntry]:
    """Everything a rig could use here; a backend that cannot be queried is skipped."""
    dev, sysfs = Path(dev_root), Path(sysfs_root)
    found = [DeviceEntry("rig", "simulated", "simulated",
                         "simulated display and camera with ground truth (hw_mocks)",
                         {"kind": "simulated"})]
    found += _framebuffers(dev, sysfs / "graphics")
    found += _sdl()
    found += _v4l2(dev, sysfs / "video4linux")
    found += _usb(usb_backend)
    if aravis_discovery or aravis_addresses:
        found += _aravis(aravis_discovery, list(aravis_addresses or []))
    return found
