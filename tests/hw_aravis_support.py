"""Test support for Aravis: skip locally / fail in CI when missing; the fake's lock.

Only one GigE Vision fake can serve 127.0.0.1 and the suite runs with pytest-xdist, so
tests hold `fake_camera_lock()` (a machine-wide file lock) while a fake runs.
"""

from __future__ import annotations

import os

import pytest

from acquisition.camera.aravis_fake import fake_camera_lock

__all__ = ["IN_CI", "fake_camera_lock", "require_aravis"]

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_aravis() -> None:
    """Skip (locally) or fail (CI) when Aravis cannot be loaded."""
    from acquisition.camera.aravis_gi import aravis, libaravis
    from acquisition.errors import CameraError

    try:
        aravis()
        libaravis()
    except CameraError as exc:
        if IN_CI:
            pytest.fail(f"Aravis is required in CI: {exc}")
        pytest.skip(str(exc))
