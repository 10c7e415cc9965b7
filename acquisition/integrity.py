"""Pose integrity: repeat reference frames at the end of a pose and compare with the originals.

References are the white flat, the dark flat and the finest cosine of the first axis.
A repeat that differs beyond noise means the pose is not one rigid, stable scene:
- dark level moved        -> ambient light changed (flicker, room light);
- white-dark contrast     -> brightness drift (auto-gain/auto-exposure, panel dimming);
- fine cosine changed more than the white flat's repeat noise allows (after gain
  correction)                -> camera or screen motion (or refocus).
Noise is measured from the data (robust spread of the white-flat repeat difference), so
the thresholds are in noise units and fractions, not in DN. Large images are compared on
a regular grid of about `MAX_COMPARED` pixels (every k-th row and column): the standard
errors stay far below the thresholds, and the check, which runs after the pose's last
frame, costs milliseconds at 5 Mpixel instead of seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calibration.shared.plan import CosineFrame, FlatFrame, Plan

MAX_COMPARED = 1 << 18  # pixels compared at most (a regular grid on larger images)


@dataclass(frozen=True)
class IntegrityThresholds:
    """Limits beyond which a pose is flagged."""

    ambient_sigma: float = 6.0  # dark-level shift, in standard errors of the mean difference
    ambient_fraction: float = 0.01  # ... and at least this fraction of the white-dark contrast
    gain_fraction: float = 0.02  # relative change of white-dark contrast
    motion_ratio: float = 2.5  # cosine repeat difference / expected repeat noise


@dataclass(frozen=True)
class IntegrityReport:
    """Result of comparing repeated reference frames; `ok` False means flag the pose."""

    ok: bool
    reasons: tuple[str, ...]
    metrics: dict[str, float] = field(default_factory=dict)
    references: tuple[int, ...] = ()

    @property
    def reason(self) -> str:
        """All failure reasons on one line ('' when ok)."""
        return "; ".join(self.reasons)


def reference_indices(plan: Plan) -> tuple[int, int, int] | None:
    """(white flat, dark flat, finest cosine) plan indices, or None if the plan lacks one."""
    flats = [(f.level, i) for i, f in enumerate(plan.frames) if isinstance(f, FlatFrame)]
    cos = [(f.period_px, i) for i, f in enumerate(plan.frames) if isinstance(f, CosineFrame)]
    if len(flats) < 2 or not cos:
        return None
    return max(flats)[1], min(flats)[1], min(cos)[1]


def _robust_sigma(x: np.ndarray) -> float:
    """Standard deviation estimated from the median absolute deviation (outlier-proof)."""
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def compare_references(
    original: tuple[np.ndarray, np.ndarray, np.ndarray],
    repeat: tuple[np.ndarray, np.ndarray, np.ndarray],
    thresholds: IntegrityThresholds | None = None,
) -> IntegrityReport:
    """Compare (white, dark, cosine) images captured at the start with their repeats."""
    th = thresholds or IntegrityThresholds()
    k = max(1, math.ceil(math.sqrt(np.asarray(original[0]).size / MAX_COMPARED)))
    w0, d0, c0 = (np.asarray(np.asarray(a)[::k, ::k], np.float64) for a in original)
    w1, d1, c1 = (np.asarray(np.asarray(a)[::k, ::k], np.float64) for a in repeat)
    contrast0 = w0 - d0
    lit = contrast0 > 0.25 * np.percentile(contrast0, 99)
    if lit.sum() < 16:
        return IntegrityReport(False, ("screen not seen: too few lit pixels in the white flat",))
    n = float(lit.sum())
    sig_w = _robust_sigma((w1 - w0)[lit]) / np.sqrt(2)  # one frame's noise at white
    sig_d = _robust_sigma((d1 - d0)[lit]) / np.sqrt(2)
    dark_shift = float(np.median((d1 - d0)[lit]))
    mean_contrast = float(np.median(contrast0[lit]))
    ambient_se = np.sqrt(2) * max(sig_d, 0.5) / np.sqrt(n) * 1.2533  # s.e. of a median
    gain = float(np.median((w1 - d1)[lit]) / mean_contrast)
    # Motion: cosine difference after gain/offset correction vs the expected repeat noise.
    c1c = d0 + (c1 - d1) / gain
    diff = (c1c - c0)[lit]
    expected = np.sqrt(2) * np.sqrt(sig_d**2 + (sig_w**2 - sig_d**2) * 0.5)
    motion = float(np.sqrt(np.mean(diff**2)) / max(expected, 0.5))
    metrics = {"dark_shift_dn": dark_shift, "dark_shift_sigma": abs(dark_shift) / ambient_se,
               "gain_ratio": gain, "motion_ratio": motion, "noise_white_dn": sig_w,
               "lit_pixels": n, "grid_step": k}
    reasons = []
    if (abs(dark_shift) / ambient_se > th.ambient_sigma
            and abs(dark_shift) > th.ambient_fraction * mean_contrast):
        reasons.append(f"ambient light changed: dark level moved {dark_shift:+.2f} DN "
                       f"({abs(dark_shift) / mean_contrast:.1%} of contrast)")
    if abs(gain - 1.0) > th.gain_fraction:
        reasons.append(f"brightness drift: white-dark contrast changed by {gain - 1:+.1%} "
                       "(auto-gain/exposure or display brightness)")
    if motion > th.motion_ratio:
        reasons.append(f"motion: fine cosine repeat differs {motion:.1f}x the noise "
                       "(camera or screen moved, or focus changed)")
    return IntegrityReport(not reasons, tuple(reasons), metrics)
