"""How much the machine itself stalls a sleeping thread, to tell its stalls from the service's.

`StallProbe` runs a separate plain Python process (normal priority, like the capture
thread) that sleeps 2 ms in a loop and reports every oversleep above 2 ms with its wall
time; `worst_ms(t0, t1)` is the longest in a window. A trigger that fires late by about
the probe's stall in the same window was late because the machine was (CPU contention,
kernel work, the hypervisor), not because of the service. `steal_ms` reads the
hypervisor's steal time from /proc/stat (Linux guests; None elsewhere).
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

_PROBE = """import time
while True:
    t0 = time.time()
    time.sleep(0.002)
    late = time.time() - t0 - 0.002
    if late > 0.002:
        print(f"{t0:.4f} {late:.4f}", flush=True)
"""


class StallProbe:
    """The probe process and the oversleeps it reported (wall time, seconds late)."""

    def __init__(self) -> None:
        self._proc = subprocess.Popen([sys.executable, "-c", _PROBE], stdout=subprocess.PIPE,
                                      text=True)
        self._events: list[tuple[float, float]] = []
        self._reader = threading.Thread(target=self._read, daemon=True, name="stall-probe")
        self._reader.start()

    def _read(self) -> None:
        assert self._proc.stdout is not None
        for line in self._proc.stdout:
            t, late = line.split()
            self._events.append((float(t), float(late)))

    def worst_ms(self, t0: float, t1: float) -> float:
        """Longest oversleep (ms) of a sleep that started between wall times t0 and t1."""
        return 1e3 * max((late for t, late in list(self._events) if t0 <= t <= t1),
                         default=0.0)

    def close(self) -> None:
        self._proc.kill()
        self._proc.wait(10)


def steal_ms() -> float | None:
    """Steal time so far (ms, all CPUs): time the hypervisor ran something else while this
    guest's virtual CPUs wanted to run; None where /proc/stat has no steal field."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()
        return 1e3 * int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None
