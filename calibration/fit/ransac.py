"""The one RANSAC loop of the closed-form estimators (homography, DLT): best minimal-sample
model by inlier count, then refits on the consensus set until it is stable."""

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
    *, iterations: int = 500, what: str = "model",
) -> tuple[M, np.ndarray]:
    """Robust fit of `n` data: `fit(indices)` a model, `errors(model)` (n,) per datum; a datum
    is an inlier when its error < threshold. Returns (model, inlier mask)."""
    if n < sample_size:
        raise DegenerateError(f"{what} needs >= {sample_size} points, got {n}")
    best = np.zeros(n, dtype=bool)
    for _ in range(iterations):
        try:
            model = fit(rng.choice(n, sample_size, replace=False))
        except DegenerateError:
            continue
        inl = errors(model) < threshold
        if inl.sum() > best.sum():
            best = inl
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
