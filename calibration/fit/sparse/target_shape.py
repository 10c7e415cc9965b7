"""The target's shape in a fit: flat as given, or bowed in x and y.

A bowed target moves each point along the target's z by
bow_x (xi^2 - 1/3) + bow_y (eta^2 - 1/3), xi and eta running over [-1, 1] across the
target points' extent: the same quadratic sag the screen fits use for a panel
(`calibration.metrology.screen_trace.ScreenTrace.depth`, whose twist term a printed board
does not need). bow_x is how far (mm, along +z = x cross y of the target frame) the
x-edges lie from the centre line; the -1/3 keeps the mean depth unchanged, so the bow
does not trade off against the pose's distance.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.metrology.screen_trace import ScreenTrace


class TargetShape:
    """Flat (no parameters) or bowed (bow_x, bow_y mm) target over fixed point extents."""

    def __init__(self, mode: str, trace: ScreenTrace) -> None:
        self.mode = mode
        self.trace = trace
        self.params = np.zeros(2 if mode == "fit" else 0)
        self.covariance = np.zeros((self.params.size, self.params.size))

    @classmethod
    def of(cls, target_xyz: np.ndarray, mode: str) -> TargetShape:
        """The shape over the extent of every target point (mm)."""
        lo, hi = target_xyz[:, :2].min(axis=0), target_xyz[:, :2].max(axis=0)
        centre, half = (lo + hi) / 2, np.maximum((hi - lo) / 2, 1e-9)
        return cls(mode, ScreenTrace(float(centre[0]), float(centre[1]), float(half[0]),
                                     float(half[1]), 1.0))

    @property
    def n_free(self) -> int:
        """Shape parameters the fit moves."""
        return self.params.size

    def points(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the shaped points (n, 3), their derivative over the parameters (n, 3, n_free))."""
        if not self.n_free:
            return xyz, np.zeros((xyz.shape[0], 3, 0))
        xi, eta, dz = self.trace.depth([*self.params, 0.0], xyz[:, 0], xyz[:, 1])
        out = xyz.copy()
        out[:, 2] += dz
        jac = np.zeros((xyz.shape[0], 3, 2))
        jac[:, 2, 0], jac[:, 2, 1] = xi * xi - 1 / 3, eta * eta - 1 / 3
        return out, jac

    def set_covariance(self, cov: np.ndarray) -> None:
        """The parameters' covariance from the fit (mm^2)."""
        self.covariance = np.asarray(cov, dtype=np.float64).reshape(self.n_free, self.n_free)

    def to_json(self) -> dict[str, Any]:
        """Mode, bows with 1-sigma (mm) and the extent they refer to."""
        out: dict[str, Any] = {"mode": self.mode,
                               "extent_mm": [2 * self.trace.ax, 2 * self.trace.ay]}
        if self.n_free:
            std = np.sqrt(np.clip(np.diag(self.covariance), 0, None))
            out.update({"bow_x_mm": float(self.params[0]), "bow_y_mm": float(self.params[1]),
                        "bow_x_std_mm": float(std[0]), "bow_y_std_mm": float(std[1])})
        return out
