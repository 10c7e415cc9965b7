"""Typed options of the pixel-space fits on target observations (every parametric model,
and the sGCC models)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, PositiveInt, StrictBool

MIN_VIEWS = 3  # a planar target: Zhang's method needs three views for K with distortion


class ObservationOptions(BaseModel):
    """Options of a fit to target observations; every field has a working default."""

    model_config = ConfigDict(extra="forbid")
    target: Literal["flat", "fit"] = Field(
        default="flat",
        description='"flat": the target points as given; "fit": a bow in x and in y (mm, '
                    "edge relative to centre) estimated with the camera")
    weights: Literal["observed", "equal"] = Field(
        default="observed",
        description='"observed": each point weighted as its file says; "equal": every used '
                    "point weighted 1 (as cv2.calibrateCamera)")
    outlier_sigma: float = Field(
        default=5.0, gt=1.0,
        description="points whose residual exceeds this many robust sigmas are outliers")
    outlier_rounds: int = Field(default=3, ge=0, le=10,
                                description="refits after dropping outliers")
    thin_prism: StrictBool = Field(default=False, description="opencv-rational: also fit s1..s4")
    cells: tuple[PositiveInt, PositiveInt] | Literal["auto"] = Field(
        default="auto",
        description='sgcc models: spline mesh [cu, cv] cells, or "auto": the finest of 10, 8, '
                    "6, 5, 4 cells along the longer side with >= 20 points in each cell "
                    "that holds points")
    max_iterations: int = Field(default=200, ge=5, le=10_000,
                                description="Levenberg-Marquardt evaluations per round")
