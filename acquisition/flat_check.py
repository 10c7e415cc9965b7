"""Flat-field check of a rig: show white and black, capture, and say what the camera sees.

Used by `phasecal check` before a session: how much of the image sees the screen with
usable contrast, and whether anything saturates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acquisition.protocols import Camera, Display

# A pixel "sees the screen" when white exceeds black by this fraction of the full scale.
MIN_CONTRAST_FRACTION = 0.05


@dataclass(frozen=True)
class FlatReport:
    """What the camera saw on a white and a black screen."""

    white_mean: float
    black_mean: float
    white_p99: float
    full_scale: int
    saturated_fraction: float  # pixels at full scale on white
    screen_fraction: float  # pixels with white - black >= MIN_CONTRAST_FRACTION * full scale

    def lines(self) -> list[str]:
        """Human-readable summary."""
        return [
            f"white: mean {self.white_mean:.1f} DN, 99th percentile {self.white_p99:.1f} DN "
            f"(full scale {self.full_scale})",
            f"black: mean {self.black_mean:.1f} DN",
            f"screen covers {100 * self.screen_fraction:.1f}% of the image; "
            f"{100 * self.saturated_fraction:.2f}% saturated on white",
        ]


def _capture(display: Display, camera: Camera, level: int, settle_flips: int,
             timeout_s: float) -> np.ndarray:
    """Show a flat, let it reach the panel (re-showing it waits one flip each), capture."""
    info = display.info
    dtype = np.uint8 if info.bit_depth == 8 else np.uint16
    image = np.full((info.height_px, info.width_px), level, dtype)
    for _ in range(settle_flips + 1):
        display.show(image)
    camera.flush()  # the next frame starts exposing after the flat is on the panel
    camera.trigger()
    return camera.grab(timeout_s).image


def check_flats(display: Display, camera: Camera, *, settle_flips: int = 3,
                timeout_s: float = 2.0) -> FlatReport:
    """Capture white and black flats (camera configured and started).

    `settle_flips`: refresh periods to wait after the flip for the display latency (the
    measured latency, rounded up, plus one for the scan-out).
    """
    top = (1 << display.info.bit_depth) - 1
    white = _capture(display, camera, top, settle_flips, timeout_s).astype(np.float64)
    black = _capture(display, camera, 0, settle_flips, timeout_s).astype(np.float64)
    full = (1 << camera.info.bit_depth) - 1
    if white.max(initial=0) > full:  # e.g. 12-bit data delivered in 16-bit words
        full = int(np.iinfo(np.uint16).max)
    return FlatReport(
        white_mean=float(white.mean()),
        black_mean=float(black.mean()),
        white_p99=float(np.percentile(white, 99)),
        full_scale=full,
        saturated_fraction=float(np.mean(white >= full)),
        screen_fraction=float(np.mean(white - black >= MIN_CONTRAST_FRACTION * full)),
    )
