"""Test support for the Aravis GigE Vision fake: one per machine at a time (file lock).

Only one fake can serve 127.0.0.1 (GVCP port 3956), and the suite runs with
pytest-xdist, so every test process takes an exclusive lock before starting one.
Under CI a missing Aravis fails the tests instead of skipping them.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
LOCK_PATH = Path(tempfile.gettempdir()) / "phasecal-aravis-fake.lock"


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


@contextlib.contextmanager
def fake_camera_lock() -> Iterator[None]:
    """Exclusive, machine-wide right to run a GigE Vision fake on 127.0.0.1."""
    with open(LOCK_PATH, "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
