"""Test support for Aravis: skip locally / fail in CI when missing; the fake's lock; a
fake whose link loses packets.

Only one GigE Vision fake can serve 127.0.0.1 and the suite runs with pytest-xdist, so
tests hold `fake_camera_lock()` (a machine-wide file lock) while a fake runs.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator

import pytest

from acquisition.camera.aravis_fake import fake_camera_lock
from acquisition.camera.aravis_gi import aravis, libaravis
from acquisition.errors import CameraError

__all__ = ["IN_CI", "fake_camera_lock", "lossy_fake_camera", "require_aravis"]

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_aravis() -> None:
    """Skip (locally) or fail (CI) when Aravis cannot be loaded."""
    try:
        aravis()
        libaravis()
    except CameraError as exc:
        if IN_CI:
            pytest.fail(f"Aravis is required in CI: {exc}")
        pytest.skip(str(exc))


@contextlib.contextmanager
def lossy_fake_camera(serial: str) -> Iterator[Callable[[float], None]]:
    """Aravis' own GigE Vision fake on 127.0.0.1 (its built-in test image); the function
    it yields sets the share of GVSP packets the fake drops at random, like a congested
    link. Aravis 0.8's fake cannot resend, so every packet it drops loses its frame. Set
    it once the camera's stream runs: Aravis sizes packets with test packets when it
    creates a first stream, and losing those leaves that stream deaf. The caller holds
    `fake_camera_lock()` and has stopped any other fake."""
    Aravis = aravis()
    gv = Aravis.GvFakeCamera.new("127.0.0.1", serial)
    if not gv.is_running():
        raise CameraError("Aravis fake camera on 127.0.0.1: not running (port 3956 in use?)")
    holder = [gv]  # the only reference: dropping it stops the fake and frees the port
    del gv
    try:
        yield lambda ratio: holder[0].set_property("gvsp-lost-ratio", ratio)
    finally:
        holder.clear()
