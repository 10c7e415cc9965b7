"""The `mover` section of a rig config: which robot or stage places the camera or the screen.

Each backend's keys are validated here (pydantic, errors naming the field); simulated
movers are built from their section by the simulator factory (`hw_mocks.rig`), a robot
server (`http`) by `open_mover`. See docs/robots.md.
"""

from __future__ import annotations

import re
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from acquisition.mover import Mover

URL_RE = re.compile(r"^https?://[^\s/?#]+(/\S*)?$")  # a robot server's


class MoverSection(BaseModel):
    """A part of the mover section: unknown keys are errors (a misspelled key is named)."""

    model_config = ConfigDict(extra="forbid")


Vec3 = tuple[float, float, float]
Limits = tuple[float, float]


def _ordered(limits: Limits, name: str) -> None:
    """A (low, high) pair must be ordered."""
    if limits[0] > limits[1]:
        raise ValueError(f"{name}: low {limits[0]:g} exceeds high {limits[1]:g}")


class WorkspaceConfig(MoverSection):
    """Where a simulated arm's flange may go: a box for its origin (base frame, mm) and
    orientations within `max_angle_deg` of the identity."""

    min_mm: Vec3
    max_mm: Vec3
    max_angle_deg: float = Field(default=180.0, gt=0, le=180)

    @model_validator(mode="after")
    def _box(self) -> WorkspaceConfig:
        for axis, lo, hi in zip("xyz", self.min_mm, self.max_mm, strict=True):
            _ordered((lo, hi), f"{axis} of min_mm/max_mm")
        return self


class MoverBase(MoverSection):
    """What every mover has: how long one move may take before it is stopped."""

    timeout_s: float = Field(default=60.0, gt=0, le=3600, allow_inf_nan=False,
                             description="a move not settled by then is stopped (MoveTimeout)")


class SimulatedMotionConfig(MoverBase):
    """A simulated mover's errors and pace (`hw_mocks.arm`); unset: the simulator's."""

    repeatability_mm: float | None = Field(default=None, ge=0, le=10)
    repeatability_deg: float | None = Field(default=None, ge=0, le=5)
    backlash_mm: float = Field(default=0.0, ge=0, le=10)
    backlash_deg: float = Field(default=0.0, ge=0, le=5)
    speed_mm_s: float = Field(default=250.0, gt=0, allow_inf_nan=False)
    speed_deg_s: float = Field(default=60.0, gt=0, allow_inf_nan=False)
    settle_s: float = Field(default=0.05, ge=0, le=60)
    seed: int = Field(default=0, ge=0, description="its random landing errors")
    mount: Literal["eye-in-hand", "eye-to-hand"] = Field(
        default="eye-in-hand",
        description="what the simulated mover carries: the camera (the screen stands still) "
                    "or the screen (the camera stands still)")


class SimulatedArmConfig(SimulatedMotionConfig):
    """A simulated six-axis arm (default workspace: +-1500 mm, any orientation)."""

    backend: Literal["simulated-arm"]
    workspace: WorkspaceConfig | None = None


class SimulatedPanTiltConfig(SimulatedMotionConfig):
    """A simulated pan-tilt head rotating about `origin_mm` (R = Rz(pan) Rx(tilt))."""

    backend: Literal["simulated-pan-tilt"]
    origin_mm: Vec3 = (0.0, 0.0, 0.0)
    pan_deg: Limits = (-90.0, 90.0)
    tilt_deg: Limits = (-45.0, 45.0)

    @model_validator(mode="after")
    def _limits(self) -> SimulatedPanTiltConfig:
        _ordered(self.pan_deg, "pan_deg")
        _ordered(self.tilt_deg, "tilt_deg")
        if max(map(abs, self.pan_deg)) > 180 or max(map(abs, self.tilt_deg)) > 90:
            raise ValueError("pan_deg must lie within [-180, 180] and tilt_deg within "
                             "[-90, 90] degrees")
        return self


class SimulatedLinearConfig(SimulatedMotionConfig):
    """A simulated linear rail: t = origin_mm + travel * direction (unit), orientation fixed."""

    backend: Literal["simulated-linear"]
    origin_mm: Vec3 = (0.0, 0.0, 0.0)
    direction: Vec3 = (1.0, 0.0, 0.0)
    travel_mm: Limits = (0.0, 1000.0)

    @model_validator(mode="after")
    def _axis(self) -> SimulatedLinearConfig:
        _ordered(self.travel_mm, "travel_mm")
        if not any(self.direction):
            raise ValueError("direction: must not be zero (the rail's axis)")
        return self


class HttpMoverConfig(MoverBase):
    """A lab's robot server speaking the HTTP/JSON protocol of `acquisition.movers.http`."""

    backend: Literal["http"]
    url: str = Field(description="the robot server, e.g. http://robot.lab:8100")
    request_timeout_s: float = Field(default=5.0, gt=0, le=600, allow_inf_nan=False)
    margin_s: float = Field(default=2.0, ge=0, le=600, allow_inf_nan=False,
                            description="beyond timeout_s before the client sends /stop")

    @field_validator("url")
    @classmethod
    def _http_url(cls, url: str) -> str:
        """An http(s) URL with a host, so the error names what is wrong."""
        if not URL_RE.match(url):
            raise ValueError(f"expected an http:// or https:// URL of the robot server "
                             f"(http://host:port), got {url!r}")
        return url


SIMULATED_MOVERS = ("simulated-arm", "simulated-pan-tilt", "simulated-linear")
MoverConfig = Annotated[SimulatedArmConfig | SimulatedPanTiltConfig | SimulatedLinearConfig
                        | HttpMoverConfig, Field(discriminator="backend")]


def open_mover(cfg: HttpMoverConfig) -> Mover:
    """Connect to a robot server from its config section (MoverError if it does not answer
    `GET /info`)."""
    from acquisition.movers.http import HttpMover  # (httpx loads only for rigs with one)

    return HttpMover(cfg.url, request_timeout_s=cfg.request_timeout_s, margin_s=cfg.margin_s)
