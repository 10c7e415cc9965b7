"""Clocks: the controller and the simulated devices share one, so tests can run on virtual time."""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    """Monotonic time source in seconds that can also wait."""

    def now(self) -> float:
        """Current time in seconds (monotonic)."""
        ...

    def sleep_until(self, t: float) -> None:
        """Block until `now() >= t` (returns at once if already past)."""
        ...


class RealClock:
    """Wall-clock time (`time.monotonic`) for real hardware and the demo."""

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t: float) -> None:
        dt = t - time.monotonic()
        if dt > 0:
            time.sleep(dt)
