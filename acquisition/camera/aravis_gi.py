"""Loading Aravis (GObject introspection and the C library) with actionable errors."""

from __future__ import annotations

import ctypes
import functools
from typing import Any

from acquisition.errors import CameraError

ARAVIS_API = "0.8"
ARAVIS_SONAME = "libaravis-0.8.so.0"
INSTALL_HINT = (
    "install Aravis: `bash scripts/install-system-deps.sh` (Debian: gir1.2-aravis-0.8) "
    "and phasecal's aravis extra: `pip install 'phasecal[aravis]'`"
)


class _LazyGLib:
    """`gi.repository.GLib`, imported on first use (so importing us never needs gi)."""

    def __getattr__(self, name: str) -> Any:
        from gi.repository import GLib as _glib

        return getattr(_glib, name)


GLib: Any = _LazyGLib()


@functools.cache
def aravis() -> Any:
    """The `Aravis` introspection module, or a CameraError saying what to install."""
    try:
        import gi

        gi.require_version("Aravis", ARAVIS_API)
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise CameraError(f"Aravis {ARAVIS_API} is not available ({exc}); {INSTALL_HINT}") from exc
    return Aravis


@functools.cache
def libaravis() -> ctypes.CDLL:
    """The Aravis C library, for the few calls introspection cannot make safely."""
    try:
        return ctypes.CDLL(ARAVIS_SONAME)
    except OSError as exc:
        raise CameraError(f"{ARAVIS_SONAME} not found ({exc}); {INSTALL_HINT}") from exc


def aravis_available() -> bool:
    """True when both the introspection data and the library load."""
    try:
        aravis()
        libaravis()
    except CameraError:
        return False
    return True
