"""Virtual time for simulated rigs: `sleep_until` jumps ahead at once (tests take no real time)."""

from __future__ import annotations

import threading


class VirtualClock:
    """A `acquisition.clock.Clock` whose time only moves when someone sleeps or advances it."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._t = float(start_s)
        self._lock = threading.Lock()

    def now(self) -> float:
        """Current virtual time in seconds."""
        with self._lock:
            return self._t

    def sleep_until(self, t: float) -> None:
        """Jump to `t` at once (no-op if `t` is already past)."""
        with self._lock:
            if t > self._t:
                self._t = float(t)

    def advance(self, dt: float) -> None:
        """Move time forward by `dt` seconds (dt >= 0)."""
        if dt < 0:
            raise ValueError(f"VirtualClock.advance: dt must be >= 0, got {dt}")
        with self._lock:
            self._t += float(dt)
