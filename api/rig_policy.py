"""What a rig created over REST may name: listed devices and recordings in the data directory,
and no robot server (a mover reached over HTTP).

Each camera of a several-camera rig is checked as a one-camera rig's camera is; errors
name it by its place (`config.cameras.1.source`).

A request body must never make the server open or write an arbitrary path (a framebuffer
"device" that is an ordinary file would be overwritten with pattern pixels), nor send
requests (robot moves) to an address it names. Rigs with
other devices or paths come only from files the operator gives the server
(`serve --rig FILE`, `serve --rigs-dir DIR`).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from acquisition.discovery import list_device_nodes
from api.problems import Problem

OPERATOR_ONLY = "give such a rig in an operator rig file (serve --rig FILE or --rigs-dir DIR)"
SDL_DRIVER_RE = re.compile(r"^[A-Za-z0-9_-]{1,32}$")


def listed_devices(dev_root: Path, sysfs_root: Path, aravis_ids: tuple[str, ...]) -> set[str]:
    """Device ids this machine lists in `GET /devices` that a rig config can name."""
    return {d.id for d in list_device_nodes(dev_root, sysfs_root)} | set(aravis_ids)


def _refuse(field: str, detail: str) -> Problem:
    return Problem(422, "forbidden-path", f"{field}: {detail}", field=field)


def recording_in_data_dir(source: str, data_dir: Path, field: str) -> str:
    """`source` as an absolute path inside `data_dir` (relative paths are taken from there).

    Refuses `..`, absolute paths outside the data directory and symlinks leading out; an
    image-sequence pattern (`frame_%04d.png`) is checked for its folder and every file it
    matches now.
    """
    from acquisition.camera.opencv_capture import is_recording

    root = data_dir.resolve()
    raw = Path(source)
    if "://" in source:
        raise _refuse(field, f"{source!r}: URLs (network streams) cannot be named over REST; "
                      + OPERATOR_ONLY)
    if ".." in raw.parts:
        raise _refuse(field, f"{source!r} contains '..'; name a recording inside the data "
                      "directory")
    if not is_recording(source):
        raise _refuse(field, f"{source!r} is neither a device listed by GET /devices nor a "
                      "recording (.mkv/.avi/.mp4/.mov or a frame_%04d.png pattern); "
                      + OPERATOR_ONLY)
    path = raw if raw.is_absolute() else root / raw
    resolved = path.parent.resolve() / path.name
    if "%" not in path.name:
        resolved = path.resolve()
    if not resolved.is_relative_to(root) or resolved == root:
        raise _refuse(field, f"{source!r} lies outside the data directory (symlinks are "
                      f"followed); recordings must be inside it, or {OPERATOR_ONLY}")
    if "%" in path.name:
        glob = re.sub(r"%0?\d*d", "*", path.name)
        for match in resolved.parent.glob(glob):
            if not match.resolve().is_relative_to(root):
                raise _refuse(field, f"{match.name} is a symlink leading out of the data "
                              "directory")
    return str(resolved)


MAX_SIM_PIXELS = 4096 * 4096  # a simulated camera's sensor (times supersample**2 when rendering)
MAX_SUPERSAMPLE = 8
MAX_SCREEN_PX = 16384


def _camera_fields(config: Any) -> list[tuple[str, Any]]:
    """(field prefix as a request names it, camera config) of every camera of a rig."""
    if config.cameras is None:
        return [("config.camera", config.camera)]
    return [(f"config.cameras.{i}", cam) for i, cam in enumerate(config.cameras)]


def _check_simulated_size(config: Any) -> None:
    """Bound what a simulated rig from a request allocates when it renders (memory)."""
    for prefix, camera in _camera_fields(config):
        _check_simulated_camera(prefix, camera.model_dump(), config.screen)


def _check_simulated_camera(prefix: str, cam: dict[str, Any], screen: Any) -> None:
    """One simulated camera's sensor and rendering within the limits."""
    values = {f"{prefix}.width": cam.get("width", 160),
              f"{prefix}.height": cam.get("height", 120),
              f"{prefix}.supersample": cam.get("supersample", 2),
              "config.screen.width_px": screen.width_px or 1,
              "config.screen.height_px": screen.height_px or 1}
    for field, v in values.items():
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise Problem(422, "invalid-rig-config", f"{field}: expected a positive integer, "
                          f"got {v!r}", field=field)
    w, h = values[f"{prefix}.width"], values[f"{prefix}.height"]
    s = values[f"{prefix}.supersample"]
    limits = ((w * h <= MAX_SIM_PIXELS, f"{prefix}.width",
               f"{w}x{h} px exceeds {MAX_SIM_PIXELS} pixels"),
              (s <= MAX_SUPERSAMPLE, f"{prefix}.supersample", f"{s} exceeds {MAX_SUPERSAMPLE}"),
              (max(values["config.screen.width_px"], values["config.screen.height_px"])
               <= MAX_SCREEN_PX, "config.screen.width_px", f"exceeds {MAX_SCREEN_PX} px"))
    for ok, field, detail in limits:
        if not ok:
            raise Problem(422, "invalid-rig-config", f"{field}: {detail} for a simulated rig "
                          f"created over REST; {OPERATOR_ONLY}", field=field)


def check_client_rig(config: Any, data_dir: Path, *, dev_root: Path = Path("/dev"),
                     sysfs_root: Path = Path("/sys/class"),
                     aravis_ids: tuple[str, ...] = ()) -> Any:
    """Refuse (422 naming the field) devices and paths a REST client may not name.

    `config` is a validated `acquisition.rig.RigConfig`; the returned copy has recording
    paths made absolute (inside the data directory).
    """
    if config.mover is not None and config.mover.backend == "http":
        raise _refuse("config.mover.url", "a robot server cannot be named over REST; "
                      + OPERATOR_ONLY)
    if config.kind == "simulated":
        _check_simulated_size(config)
        return config
    listed: set[str] | None = None

    def is_listed(device: str) -> bool:
        nonlocal listed
        if listed is None:
            listed = listed_devices(dev_root, sysfs_root, aravis_ids)
        return device in listed

    display = config.display
    if display.backend == "framebuffer":
        if display.sysfs_root is not None:
            raise _refuse("config.display.sysfs_root", f"a sysfs folder cannot be set over "
                          f"REST; {OPERATOR_ONLY}")
        if not is_listed(display.device):
            raise _refuse("config.display.device", f"{display.device!r} is not a framebuffer "
                          f"listed by GET /devices; {OPERATOR_ONLY}")
    elif display.backend == "sdl" and display.video_driver is not None:
        if not SDL_DRIVER_RE.match(display.video_driver):
            raise _refuse("config.display.video_driver",
                          f"{display.video_driver!r} is not an SDL video driver name")
    checked = [_checked_camera(prefix, camera, data_dir, dev_root, is_listed)
               for prefix, camera in _camera_fields(config)]
    if config.cameras is None:
        return config.model_copy(update={"camera": checked[0]})
    return config.model_copy(update={"cameras": checked})


def _checked_camera(prefix: str, camera: Any, data_dir: Path, dev_root: Path,
                    is_listed: Callable[[str], bool]) -> Any:
    """One camera of a client's rig: a listed device or a recording inside the data
    directory (returned with its path made absolute)."""
    if camera.backend == "opencv":
        src = camera.source
        device = str(dev_root / f"video{src}") if isinstance(src, int) else src
        if not is_listed(device):
            if isinstance(src, int):
                raise _refuse(f"{prefix}.source", f"camera index {src} ({device}) is not "
                              "listed by GET /devices")
            src = recording_in_data_dir(src, data_dir, f"{prefix}.source")
            camera = camera.model_copy(update={"source": src})
    elif camera.backend == "aravis" and not is_listed(camera.device):
        raise _refuse(f"{prefix}.device", f"{camera.device!r} is not an Aravis device "
                      "listed by GET /devices (the operator lists addresses with serve "
                      f"--aravis-address); {OPERATOR_ONLY}")
    return camera
