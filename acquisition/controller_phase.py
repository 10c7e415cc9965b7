"""Free-running cameras: restart the stream so its frames fall inside the pattern windows.

A function of the controller's `_Runner` (`acquisition.controller`), kept apart to keep
the event loop's module short.
"""

from __future__ import annotations

import math
from typing import Any

from acquisition.errors import CameraDisconnected, CameraTimeout


def rephase(runner: Any, index: int) -> None:
    """Free-running: restart the stream until its frames fall inside pattern windows.

    With a camera frame period that is a whole number of refresh periods, the offset x
    of the camera's exposure starts past a pattern's on-time is fixed modulo P. One
    pattern per camera frame needs x <= P - 2m - e; otherwise every pattern waits a
    refresh more (1.5x-2x the vsync floor). Stream start sets the phase, so restart at a
    start time chosen to put x in the middle of the window, using the start-to-frame
    delay measured on the previous restart. Best effort: faults leave the phase as is.
    """
    p, m, e = runner.period, runner.opts.margin_s, runner.settings.exposure_s
    ratio = runner.frame_period / p
    window = p - 2 * m - e
    if abs(ratio - round(ratio)) > 1e-3 or window <= 0:
        return  # the phase drifts anyway, or no exposure fits a refresh
    try:
        delay: float | None = None
        for attempt in range(runner.opts.rephase_attempts + 1):
            flip = runner.show(index)
            runner.camera.flush()
            fr = runner.camera.grab(runner.opts.grab_timeout_s)
            runner.last_seq, runner.fr_ref = fr.sequence, (fr.timestamp_s, fr.sequence)
            x = (fr.timestamp_s - (flip + runner.lat + p + m)) % p
            if x <= window or attempt == runner.opts.rephase_attempts:
                return
            runner.camera.stop()
            if delay is not None:
                # next start whose first frame lands mid-window on the vsync grid
                target = flip + runner.lat + p + m + window / 2 - delay
                now = runner.clock.now()
                runner.clock.sleep_until(target + math.ceil((now - target) / p) * p)
            started = runner.clock.now()
            runner.camera.start()
            first = runner.camera.grab(runner.opts.grab_timeout_s)
            delay = (first.timestamp_s - started) % runner.frame_period
            runner.last_seq, runner.fr_ref = first.sequence, (first.timestamp_s, first.sequence)
    except (CameraTimeout, CameraDisconnected):
        runner.last_seq, runner.fr_ref = -1, None  # run() recovers from faults itself
