"""What a rig calibration returns: the rig model with the evidence for it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from calibration.fit.rig.transforms import Transform
from calibration.models.base import jsonable
from calibration.shared.rig_model import RigModel


@dataclass
class RigResult:
    """The fitted rig, each training view's target pose in the reference frame, and JSON
    statistics (per camera and view residuals, chi-square, extrinsic sigmas, held-out views)."""

    rig: RigModel
    view_poses: dict[str, Transform]
    stats: dict[str, Any] = field(default_factory=dict)

    def json_stats(self) -> dict[str, Any]:
        """`stats` as plain JSON data (numbers, lists; NaN as null)."""
        return jsonable(self.stats)
