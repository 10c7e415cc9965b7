"""Flip timing for displays: wait on a real vsync source, or pace on a measured period.

Real vsync (an ioctl, a blocking GL swap) is preferred; each flip time is recorded and
the refresh period is re-measured from them. Without one, flips are placed on a grid of
that period on the controller's clock, so the timing contract of `Display.show` holds.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable

import numpy as np

from acquisition.clock import Clock


class VsyncPacer:
    """Returns the clock time of each flip, from a vsync wait or a period grid."""

    def __init__(
        self,
        clock: Clock,
        period_s: float,
        wait_vsync: Callable[[], bool] | None = None,
        history: int = 32,
    ) -> None:
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"refresh period must be > 0 s, got {period_s}")
        self._clock = clock
        self._nominal = period_s
        self._wait = wait_vsync
        self._flips: deque[float] = deque(maxlen=history)
        self._grid_t0: float | None = None

    @property
    def hardware(self) -> bool:
        """True while flips come from a real vsync source."""
        return self._wait is not None

    @property
    def period_s(self) -> float:
        """Measured refresh period (median of recent flip intervals), else the nominal one."""
        if self.hardware and len(self._flips) >= 3:
            d = np.diff(np.asarray(self._flips))
            d = d[(d > 0.25 * self._nominal) & (d < 1.75 * self._nominal)]
            if d.size:
                return float(np.median(d))
        return self._nominal

    def next_flip(self) -> float:
        """Block until the next flip and return its time on the clock."""
        if self._wait is not None:
            if self._wait():
                t = self._clock.now()
                self._flips.append(t)
                return t
            self._wait = None  # the driver refused: fall back to pacing from now on
        return self._paced_flip()

    def _paced_flip(self) -> float:
        now = self._clock.now()
        period = self.period_s
        if self._grid_t0 is None:
            self._grid_t0 = self._flips[-1] if self._flips else now
        k = math.floor((now - self._grid_t0) / period) + 1
        t = self._grid_t0 + k * period
        self._clock.sleep_until(t)
        return t
