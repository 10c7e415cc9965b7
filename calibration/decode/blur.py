"""Per-pixel Gaussian blur width from modulation versus period (docs/physics.md section 4).

Blur of width W on the screen scales the modulation of period T by exp(-2 pi^2 W^2 / T^2),
so `ln(B*/amplitude) = ln B0 - 2 pi^2 W^2 / T^2` is linear in 1/T^2. A weighted
straight-line fit over the periods with enough SNR (weights B^2/sigma_B^2, the inverse
variance of ln B*; B* corrected for its Rician noise bias) gives W^2 and its variance.
"""

from __future__ import annotations

import math
from types import ModuleType
from typing import Any


def fit_blur(
    xp: ModuleType,
    modulations: list[Any],
    mod_sigmas: list[Any],
    amplitudes: list[float],
    periods: list[float],
    min_snr: float,
) -> tuple[Any, Any]:
    """Blur width W (screen px, NaN where < 2 usable periods) and the 1-sigma of W^2."""
    sw = sx = sy = sxx = sxy = 0.0
    count = 0.0
    for mod, sig, amp, period in zip(modulations, mod_sigmas, amplitudes, periods, strict=True):
        use = (mod >= min_snr * sig) & (sig > 0) & (mod > 0)
        corrected = xp.sqrt(xp.maximum(mod**2 - 2.0 * sig**2, (0.5 * mod) ** 2))
        w = xp.where(use, (corrected / xp.where(sig > 0, sig, 1.0)) ** 2, 0.0)
        y = xp.log(xp.where(use, corrected, 1.0) / amp)
        x = 1.0 / period**2
        sw = sw + w
        sx = sx + w * x
        sy = sy + w * y
        sxx = sxx + w * x * x
        sxy = sxy + w * x * y
        count = count + use
    det = sw * sxx - sx * sx
    ok = (count >= 2) & (det > 0)
    safe = xp.where(ok, det, 1.0)
    slope = (sw * sxy - sx * sy) / safe
    w2 = -slope / (2.0 * math.pi**2)
    w2_sigma = xp.sqrt(sw / safe) / (2.0 * math.pi**2)
    width = xp.where(ok, xp.sqrt(xp.maximum(w2, 0.0)), xp.nan)
    return width, xp.where(ok, w2_sigma, xp.nan)
