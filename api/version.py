"""The installed phasecal version (package metadata), for `--version` and the OpenAPI info."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version


def phasecal_version() -> str:
    """The installed distribution's version, or 'unknown (not installed)' in a bare checkout."""
    try:
        return version("phasecal")
    except PackageNotFoundError:
        return "unknown (not installed)"
