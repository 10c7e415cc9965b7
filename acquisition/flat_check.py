"""Flat-field summary of a rig: from a white and a black capture, what the camera sees.

Used by `phasecal check` (the captures come from `acquisition.setup.grab_settled`, the
helper the controller's setup uses): how much of the image sees the screen with usable
contrast, and whether anything saturates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
            f"white flat: mean {self.white_mean:.1f} DN, 99th percentile {self.white_p99:.1f} "
            f"DN (full scale {self.full_scale})",
            f"black flat: mean {self.black_mean:.1f} DN",
            f"screen covers {100 * self.screen_fraction:.1f}% of the image; "
            f"{100 * self.saturated_fraction:.2f}% saturated on white",
        ]


def flat_report(white: np.ndarray, black: np.ndarray, full_scale: int) -> FlatReport:
    """Summarize a white and a black flat capture (same shape, camera DN)."""
    w = np.asarray(white, np.float64)
    b = np.asarray(black, np.float64)
    if w.shape != b.shape:
        raise ValueError(f"flats: white {w.shape} and black {b.shape} differ in shape")
    return FlatReport(
        white_mean=float(w.mean()),
        black_mean=float(b.mean()),
        white_p99=float(np.percentile(w, 99)),
        full_scale=int(full_scale),
        saturated_fraction=float(np.mean(w >= full_scale)),
        screen_fraction=float(np.mean(w - b >= MIN_CONTRAST_FRACTION * full_scale)),
    )
