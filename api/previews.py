"""PNG previews of decoded maps (x, y, sigma, mask) for quick looks in a browser."""

from __future__ import annotations

import cv2
import numpy as np

from calibration.maps import DecodedMaps

PREVIEW_KINDS = ("x", "y", "sigma", "mask")


def preview_png(maps: DecodedMaps, kind: str) -> bytes:
    """Colour-mapped PNG of one map; invalid pixels are black."""
    mask = maps.mask
    if kind == "mask":
        img = np.where(mask, 255, 0).astype(np.uint8)
        return _encode(img)
    if kind == "x":
        values = maps.x
    elif kind == "y":
        values = maps.y
    elif kind == "sigma":
        values = np.log10(np.hypot(maps.sigma_x, maps.sigma_y).astype(np.float64) + 1e-6)
    else:
        raise ValueError(f"preview kind {kind!r}: expected one of {PREVIEW_KINDS}")
    good = mask & np.isfinite(values)
    scaled = np.zeros(values.shape, np.uint8)
    if good.any():
        lo, hi = np.percentile(values[good], [1, 99])
        span = max(float(hi - lo), 1e-12)
        scaled[good] = np.clip((values[good] - lo) / span * 255.0, 0, 255).astype(np.uint8)
    colour = cv2.applyColorMap(scaled, cv2.COLORMAP_VIRIDIS)
    colour[~good] = 0
    return _encode(colour)


def _encode(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()
