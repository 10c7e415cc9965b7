"""Typed fit options of the raygrid model."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, StrictBool

MIN_POSES = 3


class RaygridOptions(BaseModel):
    """Options of the raygrid fit; every field has a working default."""

    model_config = ConfigDict(extra="forbid")
    central: StrictBool = Field(default=True, description="all rays through one point")
    grid_step: int | None = Field(
        default=None, ge=1, strict=True,
        description="table node spacing in px (default 1 up to 640x480, else 2)")
    max_iterations: int = Field(default=30, ge=1, le=10_000)
    tolerance: float = Field(default=1e-9, gt=0, description="relative cost change to stop")
    cut_sigmas: float = Field(default=8.0, gt=0, description="hard outlier cut, sigmas")
