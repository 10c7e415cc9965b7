"""Typed fit options of the OpenCV-family models (opencv5, opencv-rational, fisheye)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, StrictBool

MIN_POSES = 3


class ParametricOptions(BaseModel):
    """Options of the OpenCV-family fits; every field has a working default."""

    model_config = ConfigDict(extra="forbid")
    max_points_per_pose: int = Field(
        default=2000, ge=20,
        description="points per pose handed to OpenCV (its dense solver slows down "
                    "quadratically beyond a few thousand)")
    thin_prism: StrictBool = Field(default=False, description="opencv-rational: also fit s1..s4")
    outlier_rounds: int = Field(default=2, ge=0, le=10,
                                description="refits after dropping points beyond 5 robust sigmas")
    seed: int = Field(default=0, ge=0, description="seed of the held-out point subsampling")
