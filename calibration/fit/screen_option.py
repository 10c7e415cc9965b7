"""The screen options every model family takes: `screen` (flat or fitted) and the cover
glass's known refractive index (`calibration.metrology.screen` has the physics)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

ScreenMode = Literal["flat", "fit"]

GlassIndex = Annotated[float, Field(gt=1.0, le=2.5, strict=True,
                                    description="refractive index of the cover glass (known)")]
