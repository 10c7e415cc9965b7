"""Pydantic request/response models of the REST API (with OpenAPI examples)."""

from __future__ import annotations

from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, RootModel, create_model

from api.jobs.model import JobKind as JobKindEnum
from api.jobs.model import JobStatus as JobStatusEnum
from calibration.fit.registry import MODEL_NAMES, MODELS

ModelName = Literal[MODEL_NAMES]  # type: ignore[valid-type]  # from the model registry
# the job vocabulary of api.jobs.model, as plain string enums in the OpenAPI document
JobStatus = Literal[tuple(s.value for s in JobStatusEnum)]  # type: ignore[valid-type]
JobKind = Literal[tuple(k.value for k in JobKindEnum)]  # type: ignore[valid-type]
MAX_POINTS = 200_000
MAX_OFFSET = 1_000_000_000  # list offsets (SQLite integers overflow past 2**63)
# Numbers in request bodies are typed strictly: `false` or "1" is not a number, NaN and
# infinities are refused (JSON has none, but Python's parser accepts NaN/Infinity).
Num = Annotated[float, Field(strict=True, allow_inf_nan=False)]
Coord = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-1e9, le=1e9)]
PoseStatus = Literal[
    "pending", "capturing", "decoding", "ready", "flagged", "failed", "cancelled", "interrupted"
]


def _strict(*examples: dict[str, Any]) -> ConfigDict:
    """Config that rejects unknown fields and carries OpenAPI examples."""
    return ConfigDict(extra="forbid", json_schema_extra={"examples": list(examples)})


class ProblemDetail(BaseModel):
    """RFC 9457 problem document."""

    type: str = Field(examples=["https://phasecal.dev/problems/not-found"])
    title: str = Field(examples=["Not found"])
    status: int = Field(examples=[404])
    detail: str = Field(examples=["session 'ses_0123456789abcdef' does not exist"])
    instance: str | None = None


class Job(BaseModel):
    """A long operation and its progress."""

    id: str = Field(examples=["job_0123456789abcdef"])
    kind: JobKind
    status: JobStatus
    stage: str = Field(examples=["capture"])
    done: int = Field(examples=[12])
    total: int = Field(examples=[50])
    eta_s: float | None = Field(default=None, description="seconds left in the current stage")
    resource: str | None = Field(default=None, examples=["/calibrations/cal_0123456789abcdef"])
    session_id: str | None = None
    error: str | None = None
    result: dict[str, Any] | None = None
    created_at: float
    started_at: float | None = None
    finished_at: float | None = None


class JobPage(BaseModel):
    """One page of jobs, newest first."""

    items: list[Job]
    total: int
    limit: int
    offset: int


class Device(BaseModel):
    """A display, camera or rig found here, with the rig config section that selects it."""

    kind: str = Field(examples=["camera"])
    backend: str = Field(examples=["opencv"])
    id: str = Field(examples=["/dev/video0"])
    description: str
    config: dict[str, Any] = Field(examples=[{"backend": "opencv", "source": "/dev/video0"}])


class RigCreate(BaseModel):
    """A rig from a JSON config (the same fields as a rig TOML file)."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"name": "bench-sim", "config": {"kind": "simulated"}}
    ]})
    name: str = Field(min_length=1, max_length=200)
    config: dict[str, Any]


class Rig(BaseModel):
    """A rig: display, camera, screen geometry and settings."""

    id: str
    name: str
    config: dict[str, Any]
    simulated: bool
    created_at: float


class CameraSettingsModel(BaseModel):
    """Camera settings to read or change."""

    model_config = _strict(
        {"exposure_s": 0.01, "gain_db": 0.0, "pixel_format": "Mono8"}
    )
    exposure_s: Num | None = Field(default=None, gt=0, le=10)
    gain_db: Num | None = Field(default=None, ge=0, le=48)
    pixel_format: str | None = Field(default=None, min_length=1, max_length=32)


class ScreenPoseIn(BaseModel):
    """Where the simulated screen is: X_cam = R S + t; R from a rotation vector (Rodrigues)."""

    model_config = _strict(
        {"rvec": [0.1, -0.05, 0.0], "tvec_mm": [-130.0, -100.0, 320.0]}
    )
    rvec: list[Annotated[Num, Field(ge=-10, le=10)]] = Field(
        min_length=3, max_length=3, description="rotation vector, radians")
    tvec_mm: list[Annotated[Num, Field(ge=-1e6, le=1e6)]] = Field(
        min_length=3, max_length=3, description="translation, mm")


class SessionCreate(BaseModel):
    """A session on a rig with a plan (given, or built from a preset for the rig's screen)."""

    model_config = _strict(
        {"name": "lab-1", "preset": "fast"}
    )
    name: str = Field(default="", max_length=200)
    rig_id: str | None = Field(default=None, description="default: the server's rig")
    plan: dict[str, Any] | None = Field(default=None, description="a phasecal.plan/1 document")
    preset: str | None = Field(default=None, description="plan preset when no plan is given")


class Session(BaseModel):
    """A session: rig + pattern plan + poses."""

    id: str
    name: str
    rig_id: str | None
    frame_count: int
    plan_digest: str
    created_at: float


class CaptureRequest(BaseModel):
    """Capture one pose; optionally move the simulated screen first."""

    model_config = _strict(
        {"screen_pose": {"rvec": [0.1, 0.0, 0.0], "tvec_mm": [-130.0, -100.0, 320.0]}}
    )
    screen_pose: ScreenPoseIn | None = None
    noise_dn: float | None = Field(
        None, gt=0, le=1e4,
        description="per-frame camera noise sigma in DN; default: estimated from the residuals",
    )


class Pose(BaseModel):
    """One pose of a session."""

    id: str
    session_id: str
    index: int
    source: Literal["capture", "import"]
    status: PoseStatus
    job_id: str | None
    valid_pixels: int | None
    width: int | None
    height: int | None
    frames_done: int
    screen_pose: dict[str, Any] | None
    error: str | None
    created_at: float


class _CalibrationFields(BaseModel):
    """What every model's calibration request has besides its model and options."""

    model_config = ConfigDict(extra="forbid")
    pose_ids: list[str] | None = Field(default=None, max_length=500)
    heldout_pose_ids: list[str] = Field(default_factory=list, max_length=500)


def per_model(base: type[BaseModel], prefix: str) -> Any:
    """The discriminated union over the registry: one `<prefix>_<model>` request per model,
    whose `options` is that model's typed options (so OpenAPI shows each model's options and
    a bad option is a 422 naming the field)."""
    variants = tuple(
        create_model(f"{prefix}_{name.replace('-', '_')}", __base__=base,
                     __doc__=f"{prefix} for model {name}.",
                     model=(Literal[name], ...),
                     options=(spec.options, Field(default_factory=spec.options)))
        for name, spec in MODELS.items()
    )
    return Annotated[Union[variants], Field(discriminator="model")]  # noqa: UP007


class CalibrationCreate(RootModel[per_model(_CalibrationFields, "CalibrationCreate")]):  # type: ignore[misc]
    """Calibrate chosen poses (default: every ready pose) with one model and its options."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"model": "opencv-rational"},
        {"model": "sgcc", "pose_ids": ["pose_0123456789abcdef"], "options": {"cells": [14, 10]}},
    ]})


class IntrinsicsCreate(BaseModel):
    """Quick closed-form intrinsics from a session's poses (docs/intrinsics.md)."""

    model_config = _strict({"method": "rectangle", "source": "flats"},
                           {"method": "rotation", "source": "maps",
                            "pose_ids": ["pose_0123456789abcdef"]})
    method: Literal["rectangle", "selfcal", "rotation"]
    source: Literal["flats", "maps"] = "flats"
    pose_ids: list[str] | None = Field(default=None, max_length=500)
    square_pixels: bool = False
    zero_skew: bool = False


class Calibration(BaseModel):
    """A calibration and, once done, its statistics and exports."""

    id: str
    session_id: str
    model: ModelName
    pose_ids: list[str]
    heldout_pose_ids: list[str]
    status: Literal["queued", "running", "succeeded", "failed", "cancelled", "interrupted"]
    job_id: str | None
    stats: dict[str, Any] | None
    exports: list[str]
    error: str | None
    created_at: float


class ProjectRequest(BaseModel):
    """3D points in the model's camera frame, mm."""

    model_config = _strict(
        {"points": [[0.0, 0.0, 1000.0], [100.0, 50.0, 800.0]]}
    )
    points: list[tuple[Coord, Coord, Coord]] = Field(max_length=MAX_POINTS)


class ProjectResponse(BaseModel):
    """Pixels (u, v); null rows where the model cannot see the point."""

    pixels: list[list[float | None]]


class UnprojectRequest(BaseModel):
    """Camera pixels (u, v)."""

    model_config = _strict(
        {"pixels": [[320.0, 240.0], [10.5, 20.25]]}
    )
    pixels: list[tuple[Coord, Coord]] = Field(max_length=MAX_POINTS)


class UnprojectResponse(BaseModel):
    """Ray origins (mm) and unit directions; null rows where the model is not defined."""

    origins: list[list[float | None]]
    directions: list[list[float | None]]
