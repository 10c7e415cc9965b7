"""Pixel ranges that see no screen at any credible noise: decoded without the compiled
per-pixel pass (a camera's dark surround: 40 % of the service benchmark rig's 5 MP image,
whose finish is the pose-ready time after the last frame)."""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.decode.batch import ChunkSums
from calibration.decode.validity import REASONS

_NO_SCREEN = REASONS.index("no_screen")


def finish_dark_range(dec: Any, chunk: ChunkSums, sl: slice, planes: dict[str, np.ndarray],
                      reason: np.ndarray) -> bool:
    """If no pixel of `sl` clipped a step and every one fails the flat-contrast test even at
    the smallest credible noise (`_sees_no_screen`), write what the compiled finish would:
    reason `no_screen`, each axis's modulation of its last (finest) set, NaN in the other
    planes (the mask hides them); True then, False to leave the range to the kernel.

    Only in residual-noise mode, where the kernel's flat variances (the photon-transfer line
    or the pixel's own residual) are never below that floor; a given noise may be."""
    if dec._variance is not None or (chunk.bits is not None and chunk.bits.any()):
        return False
    if not dec._sees_no_screen(chunk).all():
        return False
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
    return True
