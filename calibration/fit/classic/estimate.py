"""Result of a closed-form intrinsics estimate, with a Monte Carlo uncertainty."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.fit.ransac import DegenerateError

PARAMS = ("fx", "fy", "cx", "cy", "skew")


def k_params(k: np.ndarray) -> dict[str, float]:
    """fx, fy, cx, cy, skew of an upper-triangular K with K[2,2] = 1."""
    return {"fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]),
            "cy": float(k[1, 2]), "skew": float(k[0, 1])}


@dataclass
class IntrinsicsEstimate:
    """K from a closed-form method, its 1-sigma uncertainty and the evidence behind it."""

    k: np.ndarray
    method: str
    n_views: int
    std: dict[str, float] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (`phasecal intrinsics` output, REST job result)."""
        return {"format": "phasecal.intrinsics/1", "method": self.method,
                "n_views": self.n_views, "camera_matrix": self.k.tolist(),
                **k_params(self.k), "std": self.std, "stats": self.stats}


def normalizer(image_size: tuple[int, int]) -> np.ndarray:
    """Pixel -> normalized coordinates (image center to 0, (W + H) / 2 to 1): conditioning
    for the linear solves; K' = T K keeps K's upper-triangular form."""
    w, h = image_size
    s = 2.0 / (w + h)
    return np.array([[s, 0, -s * (w - 1) / 2], [0, s, -s * (h - 1) / 2], [0, 0, 1.0]])


def monte_carlo_std(solve: Callable[[np.random.Generator], np.ndarray], samples: int,
                    rng: np.random.Generator) -> tuple[dict[str, float], int]:
    """Std of K's parameters over `samples` solves on perturbed inputs; and the failure count.

    `solve(rng)` redraws the inputs from their first-order distribution and returns K,
    raising DegenerateError where that draw has no solution (e.g. not positive definite).
    """
    ks, failed = [], 0
    for _ in range(samples):
        try:
            ks.append(solve(rng))
        except DegenerateError:
            failed += 1
    if len(ks) < 2:
        return {}, failed
    vals = np.array([[k_params(k)[p] for p in PARAMS] for k in ks])
    return {p: float(s) for p, s in zip(PARAMS, vals.std(axis=0, ddof=1), strict=True)}, failed
