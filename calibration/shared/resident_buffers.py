"""Page-aligned anonymous buffers a long-lived process keeps between decodes.

A live decode writes its maps (~205 MB at 5 MP) into memory before they go to disk. Pages
the process has not touched before cost a first-touch fault each: ~0.1 CPU s per 200 MB on
bare metal and seconds on a VM whose host took the memory back, paid after the pose's
last frame by every camera of a rig at once. A buffer given back here (`give`) serves the
next decode of the same size (`take`) with its pages resident. Bounded: at most `KEEP`
buffers (a rig's cameras decoding at once), those of another size dropped when a size no
kept buffer serves is asked for, all dropped after `KEEP_S` seconds without a `give`.
"""

from __future__ import annotations

import mmap
import threading

KEEP = 4
KEEP_S = 120.0


class ResidentBuffers:
    """The kept buffers of this process."""

    def __init__(self, keep: int = KEEP, keep_s: float = KEEP_S) -> None:
        self.keep, self.keep_s = keep, keep_s
        self._kept: list[mmap.mmap] = []
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None

    def take(self, nbytes: int) -> mmap.mmap:
        """A writable, page-aligned buffer of `nbytes` bytes (contents undefined)."""
        with self._lock:
            for i, buf in enumerate(self._kept):
                if len(buf) == nbytes:
                    return self._kept.pop(i)
            self._kept.clear()  # another size is decoded now
        return mmap.mmap(-1, nbytes)

    def give(self, buf: mmap.mmap) -> None:
        """Keep `buf` (no view of it is used again) for the next `take` of its size."""
        with self._lock:
            self._kept.append(buf)
            del self._kept[:-self.keep]
            if self._timer is not None:
                self._timer.cancel()
            self._timer = threading.Timer(self.keep_s, self.release)
            self._timer.daemon = True
            self._timer.start()

    def release(self) -> None:
        """Drop the kept buffers (their memory goes back to the OS)."""
        with self._lock:
            self._kept.clear()
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None

    def kept_bytes(self) -> int:
        with self._lock:
            return sum(len(b) for b in self._kept)


RESIDENT = ResidentBuffers()
