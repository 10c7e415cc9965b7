"""Per-pose observations shared by the generic fits (sGCC, raygrid): pixels, screen mm, sigmas."""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import ScreenGeometry


@dataclass
class PoseObs:
    """The decoded points of one pose: pixels (N,2), screen mm (N,2), sigma mm (N,2)."""

    pixels: np.ndarray
    screen_mm: np.ndarray
    sigma_mm: np.ndarray


def observations(maps: Sequence[DecodedMaps], screen: ScreenGeometry) -> list[PoseObs]:
    """Valid pixels of each pose (raster order) with screen points and sigmas converted to
    mm; a pixel is valid where the mask is set and its coordinates and sigmas are finite
    (sigmas > 0). Checked on the 2-D maps, then gathered by flat index (no (N, 2) stacks)."""
    pitch = np.asarray(screen.pitch_mm, dtype=np.float64)
    if len(maps) < 2:
        return [_pose_observations(m, pitch) for m in maps]
    with ThreadPoolExecutor(min(len(maps), 4)) as pool:  # NumPy releases the GIL here
        return list(pool.map(lambda m: _pose_observations(m, pitch), maps))


def _pose_observations(m: DecodedMaps, pitch: np.ndarray) -> PoseObs:
    """`observations` of one pose."""
    valid = m.mask & np.isfinite(m.x) & np.isfinite(m.y)
    for sig in (m.sigma_x, m.sigma_y):
        valid &= (sig > 0) & (sig < np.inf)
    flat = np.flatnonzero(valid)
    w = m.shape[1]
    pixels = np.empty((len(flat), 2))
    pixels[:, 1], pixels[:, 0] = np.divmod(flat, w)
    screen_mm, sigma_mm = np.empty((len(flat), 2)), np.empty((len(flat), 2))
    for k, (pos, sig) in enumerate(((m.x, m.sigma_x), (m.y, m.sigma_y))):
        np.multiply(np.ravel(pos)[flat], pitch[k], out=screen_mm[:, k])
        np.multiply(np.ravel(sig)[flat].astype(np.float64), pitch[k], out=sigma_mm[:, k])
    return PoseObs(pixels, screen_mm, sigma_mm)
