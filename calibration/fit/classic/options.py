"""Typed fit options of the OpenCV-family models (opencv5, opencv-rational, fisheye)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool, model_validator

from calibration.fit.screen_option import GlassIndex, ScreenMode

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
    points: Literal["all", "sampled"] = Field(
        default="all",
        description='"all": refine on every valid pixel weighted by its decoded sigma; '
                    '"sampled": OpenCV\'s fit on max_points_per_pose points only')
    screen: ScreenMode = Field(
        default="flat",
        description='"flat": an ideal bare flat screen; "fit": panel bow/twist and cover-glass '
                    "thickness estimated with the camera (needs points \"all\")")
    glass_index: GlassIndex = 1.52

    @model_validator(mode="after")
    def _screen_needs_all_points(self) -> ParametricOptions:
        """The screen model is estimated only by the weighted fit on every pixel."""
        if self.screen == "fit" and self.points != "all":
            raise ValueError('screen "fit" needs options.points = "all" (the weighted fit)')
        return self
