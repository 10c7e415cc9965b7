"""The ground-truth camera interface of the simulator and the helpers every truth camera uses.

Conventions (docs/formats.md): pixel centers at integers, top-left pixel center (0, 0);
camera frame x right, y down, z forward; millimetres.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

NEWTON_ITERS = 50
# Newton stops once steps fall below this (normalized units); being quadratic, the
# remaining error is then far below 1e-12 px.
STEP_TOL = 1e-11


class TruthCamera(ABC):
    """A ground-truth camera: per-pixel rays and the projection of 3-D points."""

    width: int
    height: int
    is_central: bool

    @abstractmethod
    def rays(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coords (any shape) -> (origins (...,3) mm, unit directions (...,3)); NaN: none."""

    @abstractmethod
    def project(self, points: np.ndarray) -> np.ndarray:
        """Points (N,3) mm in the camera frame -> pixels (N,2); NaN rows where not imaged."""

    def in_image(self, uv: np.ndarray) -> np.ndarray:
        """Whether pixel coordinates (...,2) lie on the sensor [-0.5, W-0.5] x [-0.5, H-0.5]."""
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)

    def pixel_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """(H,W) u and v coordinates of all pixel centers."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        return u, v


def normalize(d: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis."""
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def as_points(points: np.ndarray) -> np.ndarray:
    """Validate and convert an (N,3) point array to float64."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {p.shape}")
    return p
