"""Typed options of the joint rig fit (each camera's model options are its own model's)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class RigOptions(BaseModel):
    """Options of the joint fit; every field has a working default."""

    model_config = ConfigDict(extra="forbid")
    max_points_per_view: int = Field(
        default=1500, ge=20,
        description="decoded pixels per camera and view in the joint fit, spread evenly over "
                    "the image (best sigma per cell); target observations are all used")
    outlier_sigmas: float = Field(
        default=5.0, gt=2.0, description="points beyond this many robust sigmas are dropped")
    max_iterations: int = Field(default=100, ge=5, le=10_000)
    seed: int = Field(default=0, ge=0, description="seed of the robust pose starts")
