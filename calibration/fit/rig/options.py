"""Typed options of the joint rig fit (each camera's model options are its own model's)."""

from __future__ import annotations

from typing import Any

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


def split_rig_options(options: dict[str, Any] | None) -> tuple[dict[str, Any], dict[str, Any]]:
    """One flat option set (CLI `--option`, REST `options`) split into the joint fit's own
    keys and the rest, which go to every camera's model."""
    rig = {k: v for k, v in (options or {}).items() if k in RigOptions.model_fields}
    return rig, {k: v for k, v in (options or {}).items() if k not in rig}
