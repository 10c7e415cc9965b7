"""Optional dependencies (pip extras of phasecal): which extra a backend needs, whether it is
installed, and the exact command that installs it."""

from __future__ import annotations

import importlib.util

# extra -> (module that must import, what needs it)
EXTRAS: dict[str, tuple[str, str]] = {
    "aravis": ("gi", "Aravis (GenICam) cameras, through PyGObject"),
    "sdl": ("pygame", "the SDL full-screen display backend"),
    "usb": ("usb", "USB camera discovery and USB trigger boxes (pyusb)"),
    "dask": ("distributed", "running jobs on a Dask cluster"),
    "gpu": ("cupy", "the sGCC GPU path (CuPy)"),
    "bluesky": ("ophyd_async", "phasecal as Bluesky devices (bluesky, ophyd-async)"),
}


class MissingExtra(ImportError):
    """An optional dependency is not installed; the message has the install command."""


def install_command(extras: list[str]) -> str:
    """The pip command installing phasecal's `extras` (with the project's version pins)."""
    names = ",".join(sorted(set(extras)))
    return (f"pip install 'phasecal[{names}]' (in a source checkout: "
            f".venv/bin/pip install -c constraints.txt -e '.[{names}]')")


def installed(extra: str) -> bool:
    """True when the extra's module can be imported."""
    module = EXTRAS[extra][0]
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def missing_message(extras: list[str], what: str) -> str:
    """One line: what needs which missing extras, and how to install them."""
    parts = "; ".join(f"{e}: {EXTRAS[e][1]}" for e in sorted(set(extras)))
    return (f"{what} needs the optional dependencies of the extra(s) {parts}; install with: "
            f"{install_command(extras)}")


def require(extra: str, what: str | None = None) -> None:
    """Raise `MissingExtra` naming the install command unless `extra` is installed."""
    if not installed(extra):
        raise MissingExtra(missing_message([extra], what or EXTRAS[extra][1]))
