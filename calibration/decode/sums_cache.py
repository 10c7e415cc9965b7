"""The decoder's full-image sums, kept by a long-lived worker process between poses.

A 5 MP pose's sums (~1 GB: 48 float32 rows per pixel and the flats) cost up to ~2.3 CPU s
of first-touch page faults when allocated afresh on a VM (memory the guest handed back to
the host), while the capture's first frames arrive; zeroing the previous pose's arrays
again costs ~0.04 s. Each finished decode's arrays are kept (`keep`) as one set and handed
to the next decoders that ask for the same shapes and dtypes (`take`): a rig decoding 2-4
cameras of one size at once gets one set per camera, pose after pose (keeping only the last
decode's set left every camera but one paging in fresh sums, ~0.5-0.7 CPU s each at 5 MP).

Bounded: at most `MAX_SETS` sets (the oldest dropped first), so a process holds no more
than the sums of the decodes it ran at once (up to a 4-camera rig) besides those it runs; a
set a decoder took from is dropped with its unused arrays at the next `keep`; a request no
kept array serves drops the sets of other image sizes (another camera or rig is decoded
now); everything is dropped after `KEEP_S` seconds without a `keep`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

KEEP_S = 120.0
MAX_SETS = 4  # finished decodes whose sums are kept (a rig's cameras decoding at once)


@dataclass
class KeptSet:
    """One finished decode's arrays; `taken`: a decoder has taken some of them (the rest are
    arrays it did not need, dropped at the next `keep`)."""

    arrays: list[np.ndarray] = field(default_factory=list)
    taken: bool = False


_lock = threading.Lock()
_sets: list[KeptSet] = []  # oldest first
_timer: threading.Timer | None = None


def take(shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """An array of `shape` and `dtype` (contents undefined): a kept one that matches, else a
    new one (and the kept sets of other image sizes are dropped)."""
    want, shape = np.dtype(dtype), tuple(shape)
    with _lock:
        for kept in _sets:
            for i, arr in enumerate(kept.arrays):
                if arr.shape == shape and arr.dtype == want:
                    kept.taken = True
                    return kept.arrays.pop(i)
        pixels = shape[-1] if shape else 1
        _sets[:] = [s for s in _sets if all(a.shape[-1] == pixels for a in s.arrays)]
    return np.empty(shape, dtype=want)


def keep(arrays: list[Any]) -> None:
    """Keep `arrays` (a finished decoder's sums, never used by it again) as one set for the
    next `take`s, beside the sets of decodes that ran at the same time (at most `MAX_SETS`);
    all are dropped after `KEEP_S` seconds without a `keep`."""
    global _timer
    arrays = [a for a in arrays if isinstance(a, np.ndarray) and a.size]
    with _lock:
        _sets[:] = [s for s in _sets if not s.taken and s.arrays]
        if arrays:
            _sets.append(KeptSet(arrays))
        del _sets[:-MAX_SETS]
        if _timer is not None:
            _timer.cancel()
        _timer = threading.Timer(KEEP_S, release)
        _timer.daemon = True
        _timer.start()


def release() -> None:
    """Drop the kept arrays (their memory goes back to the OS)."""
    with _lock:
        _sets.clear()


def kept_arrays() -> list[np.ndarray]:
    """The arrays kept for the next decodes, oldest set first."""
    with _lock:
        return [a for s in _sets for a in s.arrays]


def holds_pixels(pixels: int, sets: int = 1) -> bool:
    """True when at least `sets` kept sets are decodes' of images of `pixels` pixels (those
    of another camera would be dropped by the next `take`, not reused)."""
    with _lock:
        return sum(any(a.shape[-1] == pixels for a in s.arrays) for s in _sets) >= sets


def kept_bytes() -> int:
    """Bytes held for the next decodes."""
    with _lock:
        return sum(a.nbytes for s in _sets for a in s.arrays)
