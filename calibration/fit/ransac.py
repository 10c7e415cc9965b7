"""The one RANSAC loop of the closed-form estimators (homography, DLT): best minimal-sample
model by inlier count, then refits on the consensus set until it is stable.

Adaptive termination: once the best model has inlier ratio w, N = log(1 - p) / log(1 - w^s)
samples of size s find an all-inlier sample with probability p (`confidence`); the loop
stops there, or at `iterations`. (OpenCV's USAC does the same for homographies and PnP:
`classic.robust`.)"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import numpy as np

M = TypeVar("M")

_REFITS = 10  # consensus refits (minimal samples extrapolate poorly)


class DegenerateError(ValueError):
    """The data do not determine the model (collinear points, too few of them, ...)."""


def ransac(
    n: int, sample_size: int, fit: Callable[[np.ndarray], M],
    errors: Callable[[M], np.ndarray], threshold: float, rng: np.random.Generator,
    *, iterations: int = 10000, confidence: float = 0.999, what: str = "model",
    stats: dict[str, float] | None = None,
) -> tuple[M, np.ndarray]:
    """Robust fit of `n` data: `fit(indices)` a model, `errors(model)` (n,) per datum; a datum
    is an inlier when its error < threshold. Returns (model, inlier mask). At most
    `iterations` samples, fewer by adaptive termination; `stats` (if given) gets `samples`."""
    if n < sample_size:
        raise DegenerateError(f"{what} needs >= {sample_size} points, got {n}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence: expected 0 < p < 1, got {confidence}")
    best = np.zeros(n, dtype=bool)
    needed, drawn = float(iterations), 0
    while drawn < min(needed, iterations):
        drawn += 1
        try:
            model = fit(rng.choice(n, sample_size, replace=False))
        except DegenerateError:
            continue
        inl = errors(model) < threshold
        if inl.sum() > best.sum():
            best = inl
            needed = required_iterations(float(inl.mean()), sample_size, confidence)
    if stats is not None:
        stats["samples"] = drawn
    if best.sum() < sample_size:
        raise DegenerateError(f"RANSAC {what}: no consensus set of >= {sample_size} inliers")
    inl = best
    for _ in range(_REFITS):
        model = fit(np.flatnonzero(inl))
        new = errors(model) < threshold
        if new.sum() < sample_size or np.array_equal(new, inl):
            break
        inl = new
    return model, inl


def required_iterations(inlier_ratio: float, sample_size: int, confidence: float) -> float:
    """Samples needed to draw one all-inlier sample with probability `confidence`."""
    good = inlier_ratio**sample_size
    if good >= 1.0:
        return 1.0
    if good <= 0.0:
        return float("inf")
    return float(np.log(1 - confidence) / np.log1p(-good))
