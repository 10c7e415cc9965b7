"""Per-pose observations shared by the generic fits (sGCC, raygrid): pixels, screen mm, sigmas."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calibration.maps import DecodedMaps
from calibration.plan import ScreenGeometry


@dataclass
class PoseObs:
    """The decoded points of one pose: pixels (N,2), screen mm (N,2), sigma mm (N,2)."""

    pixels: np.ndarray
    screen_mm: np.ndarray
    sigma_mm: np.ndarray


def observations(maps: Sequence[DecodedMaps], screen: ScreenGeometry) -> list[PoseObs]:
    """Valid pixels of each pose with screen points and sigmas converted to mm."""
    pitch = np.asarray(screen.pitch_mm, dtype=np.float64)
    out = []
    for m in maps:
        pix, scr, sig = m.correspondences()
        ok = np.all(np.isfinite(scr), axis=1) & np.all(np.isfinite(sig) & (sig > 0), axis=1)
        out.append(PoseObs(pix[ok], scr[ok] * pitch, sig[ok] * pitch))
    return out
