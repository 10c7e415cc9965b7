"""Equidistant fisheye ground-truth camera (r = f theta) of the simulator."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hw_mocks.camera_base import NEWTON_ITERS, STEP_TOL, TruthCamera, as_points

# -- equidistant fisheye ---------------------------------------------------------------


def fisheye_theta_d(k: Sequence[float], theta: np.ndarray | float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The OpenCV fisheye lens polynomial: the distorted angle theta_d = theta (1 + k1 theta^2
    + ... + k4 theta^8) of rays at `theta` radians from the axis, and its derivative (image
    radius r = f theta_d, so the derivative must stay positive across the field of view)."""
    k1, k2, k3, k4 = k
    t = np.asarray(theta, dtype=np.float64)
    t2 = t * t
    poly = 1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    dpoly = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
    return t * poly, dpoly


@dataclass
class EquidistantFisheye(TruthCamera):
    """Equidistant fisheye (OpenCV fisheye model): r = f * theta * (1 + k1 t^2 + ... k4 t^8).

    `fov_deg` is the full cone angle the lens accepts; rays beyond fov/2 are not imaged.
    """

    width: int
    height: int
    f: float
    cx: float
    cy: float
    k: Sequence[float] = (0.0, 0.0, 0.0, 0.0)
    fov_deg: float = 180.0
    is_central: bool = field(default=True, init=False)

    def __post_init__(self) -> None:
        """Validate and normalize the fields (errors name the field and what was expected)."""
        kk = np.asarray(self.k, dtype=np.float64).ravel()
        if kk.size != 4:
            raise ValueError(f"EquidistantFisheye.k: expected 4 coefficients, got {kk.size}")
        if not 0 < self.fov_deg < 360:
            raise ValueError(f"EquidistantFisheye.fov_deg: expected (0, 360), got {self.fov_deg}")
        self._k = kk
        self._theta_max = np.radians(self.fov_deg) / 2
        t = np.linspace(0.0, self._theta_max, 20001)
        dtd = fisheye_theta_d(self._k, t)[1]
        if np.any(dtd <= 0):
            raise ValueError("EquidistantFisheye.k: theta_d(theta) must increase within the FOV")

    def rays(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coords -> (zero origins, unit directions); NaN outside the lens' FOV."""
        d, theta = self.directions_unclipped(u, v)
        d[theta > self._theta_max + 1e-12] = np.nan
        return np.zeros_like(d), d

    def directions_unclipped(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray directions (...,3) and angles theta by the lens formula, ignoring the FOV.

        NaN only where theta_d(theta) cannot be inverted (beyond the polynomial's range).
        """
        du = (np.asarray(u, dtype=np.float64) - self.cx) / self.f
        dv = (np.asarray(v, dtype=np.float64) - self.cy) / self.f
        td = np.hypot(du, dv)
        theta = td.copy()
        for _ in range(NEWTON_ITERS):
            val, der = fisheye_theta_d(self._k, theta)
            step = (val - td) / der
            theta = theta - step
            if np.nanmax(np.abs(step), initial=0.0) < STEP_TOL:
                break
        with np.errstate(invalid="ignore", divide="ignore"):
            cphi = np.where(td > 0, du / td, 1.0)
            sphi = np.where(td > 0, dv / td, 0.0)
        st = np.sin(theta)
        d = np.stack([st * cphi, st * sphi, np.cos(theta)], axis=-1)
        residual = np.abs(fisheye_theta_d(self._k, theta)[0] - td)
        solved = (residual < 1e-12) & (theta >= 0) & (theta < np.pi)
        d[~solved] = np.nan
        return d, theta

    def project_unclipped(self, points: np.ndarray) -> np.ndarray:
        """Projection by the lens formula for any direction, ignoring FOV and sensor limits."""
        p = as_points(points)
        rxy = np.hypot(p[:, 0], p[:, 1])
        theta = np.arctan2(rxy, p[:, 2])
        td, _ = fisheye_theta_d(self._k, theta)
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(rxy > 0, td / rxy, 0.0)
        return np.stack([self.f * scale * p[:, 0] + self.cx, self.f * scale * p[:, 1] + self.cy], 1)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Points (any direction within the FOV cone) -> pixels; NaN if not imaged."""
        p = as_points(points)
        uv = self.project_unclipped(p)
        theta = np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2])
        ok = (theta <= self._theta_max) & self.in_image(uv) & (np.linalg.norm(p, axis=1) > 0)
        uv[~ok] = np.nan
        return uv


def wide_fisheye(width: int = 640, height: int = 480, fov_deg: float = 150.0) -> EquidistantFisheye:
    """A fisheye whose farther left/right image edge sees rays at fov/2 from the axis."""
    k = (0.012, -0.004, 0.0008, -0.0001)
    cx, cy = (width - 1) / 2 + 0.004 * width, (height - 1) / 2 + 0.006 * height
    theta_d_edge, _ = fisheye_theta_d(k, np.radians(fov_deg) / 2)
    edge_px = max(cx + 0.5, width - 0.5 - cx) + 1e-6
    f = edge_px / float(theta_d_edge)
    return EquidistantFisheye(width, height, f, cx, cy, k, fov_deg)
