"""Typed fit options of the sGCC models (sgcc, sgcc-noncentral)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, PositiveInt, field_validator

from calibration.fit.screen_option import GlassIndex, ScreenMode
from calibration.models.sgcc import DEFAULT_CELLS

MIN_POSES = 3


class SgccOptions(BaseModel):
    """Options of the sGCC fit; every field has a working default."""

    model_config = ConfigDict(extra="forbid")
    cells: tuple[PositiveInt, PositiveInt] | Literal["auto"] = Field(
        default=DEFAULT_CELLS,
        description='spline mesh [cu, cv] (a single integer n means [n, n]), or "auto": the '
                    "coarsest of 10/14/20 cells along the longer side that fits as well as the "
                    "best on validation points")
    max_iterations: int = Field(default=60, ge=1, le=10_000)
    huber_k: float = Field(default=3.0, gt=0, description="Huber threshold, sigmas")
    cut_sigmas: float = Field(default=8.0, gt=0, description="hard outlier cut, sigmas")
    smooth: float = Field(default=1e-10, ge=0,
                          description="relative weight of the second-difference prior")
    xp: Literal["numpy", "cupy"] = Field(
        default="numpy", description='"numpy": threaded CPU; "cupy": per-pixel work on a GPU')
    family_prior: Literal["off", "auto"] | None = Field(
        default=None,
        description='"auto": where a dense parametric fit (opencv5, fisheye or opencv-rational) '
                    "is as good as the free spline (likelihood-ratio test), refit with a prior "
                    "on the deviation from that family's ray field, the family's parameters "
                    "free, and report the covariance of that estimate (data noise plus the "
                    'family\'s own curvature); "off": the free spline. Default (null): "auto" '
                    'for sgcc with screen "flat", else "off" (docs/generic.md)')

    screen: ScreenMode = Field(
        default="flat",
        description='"flat": an ideal bare flat screen; "fit": panel bow/twist and cover-glass '
                    "thickness estimated jointly with the spline and the poses")
    glass_index: GlassIndex = 1.52

    @field_validator("cells", mode="before")
    @classmethod
    def _mesh(cls, v: object) -> object:
        """"auto", a pair of positive integers, or one (n means an n x n mesh)."""
        pair = (v, v) if isinstance(v, int) else v
        if v == "auto" or (isinstance(pair, list | tuple) and len(pair) == 2 and all(
                isinstance(c, int) and not isinstance(c, bool) and c >= 1 for c in pair)):
            return pair
        raise ValueError('expected [cu, cv] positive integers or "auto" (or one integer n)')
