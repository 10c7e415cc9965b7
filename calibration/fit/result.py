"""What every calibration returns, parametric or generic: the model, poses and statistics."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.models.base import CameraModel


@dataclass
class PoseEstimate:
    """Screen pose j: a screen point S (mm, z = 0) maps to the camera frame as R S + t."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,) mm
    rms_px: float | None = None  # RMS reprojection error of this pose, camera px
    rms_screen_px: float | None = None  # RMS residual in the screen plane, screen px
    n_points: int = 0


@dataclass
class CalibrationResult:
    """A fitted model with the evidence for it.

    `stats` is JSON data for reports and the API: at least `rms_px` (overall),
    `per_pose` (list of dicts), `param_std` (name -> std) where available,
    `heldout` (error on poses not used in the fit) when requested, `iterations`,
    `converged` and `wall_s`. `residuals` maps pose index -> (N, 2) pixel residuals at
    `residual_pixels[pose]` (N, 2), for residual maps and plots.
    """

    model: CameraModel
    poses: list[PoseEstimate]
    stats: dict[str, Any] = field(default_factory=dict)
    residual_pixels: dict[int, np.ndarray] = field(default_factory=dict)
    residuals: dict[int, np.ndarray] = field(default_factory=dict)
