"""The decoder's full-image sums, kept by a long-lived worker process between poses.

A 5 MP pose's sums (~1 GB: 48 float32 rows per pixel and the flats) cost up to ~2.3 CPU s
of first-touch page faults when allocated afresh on a VM (memory the guest handed back to
the host), while the capture's first frames arrive; zeroing the previous pose's arrays
again costs ~0.04 s. One decode's arrays are kept (`keep`) and handed to the next decoder
that asks for the same shapes and dtypes (`take`); a request they cannot serve drops them
all, and they are dropped after `KEEP_S` seconds unused: a process holds at most one
finished decode's sums besides those of the decodes it runs.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

KEEP_S = 120.0
_lock = threading.Lock()
_kept: list[np.ndarray] = []
_timer: threading.Timer | None = None


def take(shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """An array of `shape` and `dtype` (contents undefined): a kept one that matches, else a
    new one (and the kept ones are dropped: another camera or plan is decoded now)."""
    want = np.dtype(dtype)
    with _lock:
        for i, arr in enumerate(_kept):
            if arr.shape == tuple(shape) and arr.dtype == want:
                return _kept.pop(i)
        _kept.clear()
    return np.empty(shape, dtype=want)


def keep(arrays: list[Any]) -> None:
    """Keep `arrays` (a finished decoder's sums, never used by it again) for the next `take`s,
    in place of any kept before; they are dropped after `KEEP_S` seconds without a `keep`."""
    global _timer
    with _lock:
        _kept[:] = [a for a in arrays if isinstance(a, np.ndarray) and a.size]
        if _timer is not None:
            _timer.cancel()
        _timer = threading.Timer(KEEP_S, release)
        _timer.daemon = True
        _timer.start()


def release() -> None:
    """Drop the kept arrays (their memory goes back to the OS)."""
    with _lock:
        _kept.clear()


def holds_pixels(pixels: int) -> bool:
    """True when the kept arrays are a decode's of images of `pixels` pixels (those of
    another camera would be dropped by the next `take`, not reused)."""
    with _lock:
        return any(a.shape[-1] == pixels for a in _kept)


def kept_bytes() -> int:
    """Bytes held for the next decode."""
    with _lock:
        return sum(a.nbytes for a in _kept)
