"""Device codes of a plan's patterns, kept per display across poses.

Every pose of a session shows the same patterns, and rendering one (cosine, dither, gamma
pre-compensation) costs ~10 ms of CPU at 640x400, more on larger panels: the capture
loop would pay it for every pattern of every pose, on the cores the decoding needs.
Deterministic renderings (no dither or ordered dither) are kept, up to `MAX_BYTES` per
display (the first patterns of a plan that does not fit are kept, the rest rendered).
"""

from __future__ import annotations

import threading
import weakref
from typing import Any

import numpy as np

from acquisition.patterns import DisplayResponse, render_frame
from calibration.shared.plan import Plan

MAX_BYTES = 256 << 20
_caches: weakref.WeakKeyDictionary[Any, PatternCache] = weakref.WeakKeyDictionary()
_guard = threading.Lock()


class PatternCache:
    """Rendered codes by (plan digest, index, bit depth, dither) for one display."""

    def __init__(self, max_bytes: int = MAX_BYTES) -> None:
        self.max_bytes = max_bytes
        self.nbytes = 0
        self._entries: dict[tuple, tuple[DisplayResponse | None, np.ndarray]] = {}
        self._lock = threading.Lock()

    def codes(self, plan: Plan, digest: str, index: int, *, bit_depth: int,
              response: DisplayResponse | None, dither: str | None) -> np.ndarray:
        """The codes of plan frame `index` (read-only), rendered on the first request."""
        key = (digest, index, bit_depth, dither)
        with self._lock:
            hit = self._entries.get(key)
        if hit is not None and hit[0] is response:  # same measured response object
            return hit[1]
        codes = render_frame(plan, index, bit_depth=bit_depth, response=response, dither=dither)
        if dither not in (None, "ordered"):
            return codes  # random dither: a new draw every time
        codes.flags.writeable = False
        with self._lock:
            old = self._entries.pop(key, None)
            self.nbytes -= old[1].nbytes if old is not None else 0
            if self.nbytes + codes.nbytes <= self.max_bytes:
                self._entries[key] = (response, codes)
                self.nbytes += codes.nbytes
        return codes


def cache_for(display: Any) -> PatternCache:
    """The display's cache (a fresh, unshared one if the display cannot be weakly keyed)."""
    with _guard:
        try:
            cache = _caches.get(display)
            if cache is None:
                cache = _caches[display] = PatternCache()
        except TypeError:
            return PatternCache()
    return cache
