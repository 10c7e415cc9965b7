"""Pixel ranges that see no screen at any credible noise: decoded without the compiled
per-pixel pass (a camera's dark surround: 40 % of the service benchmark rig's 5 MP image,
whose finish is the pose-ready time after the last frame). The decoder decides which
ranges qualify (`StreamingDecoder`); this writes what the compiled finish would."""

from __future__ import annotations

import numpy as np

from calibration.decode.batch import ChunkSums
from calibration.decode.validity import REASONS

_NO_SCREEN = REASONS.index("no_screen")


def write_dark_range(chunk: ChunkSums, sl: slice, planes: dict[str, np.ndarray],
                     reason: np.ndarray) -> None:
    """Write the compiled finish's outputs for the pixel range `sl` whose pixels all see no
    screen: reason `no_screen`, each axis's modulation of its last (finest) set, NaN in the
    other planes (the mask hides them)."""
    for plane in planes.values():
        plane[:, sl] = np.nan
    last = {s.layout.axis: s for s in chunk.sets}  # set order: the last set of each axis
    for row, axis in enumerate(("x", "y")):
        s = last.get(axis)
        if s is not None:  # kernel_sums._set_block's modulation: float32 throughout there
            scale = np.float32(2.0 / s.layout.steps)  # (numba's float() of a float32 is one)
            a, b = s.a * scale, s.b * scale
            planes["modulation"][row, sl] = np.sqrt(a * a + b * b)
    reason[sl] = _NO_SCREEN
