"""Pydantic request/response models of the REST API (with OpenAPI examples)."""

from __future__ import annotations

from typing import Annotated, Any, Literal, Union

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, RootModel, create_model

from api.jobs.model import JobKind as JobKindEnum
from api.jobs.model import JobStatus as JobStatusEnum
from calibration import MODEL_NAMES, MODELS

ModelName = Literal[MODEL_NAMES]  # type: ignore[valid-type]  # from the model registry
# the job vocabulary of api.jobs.model, as plain string enums in the OpenAPI document
JobStatus = Literal[tuple(s.value for s in JobStatusEnum)]  # type: ignore[valid-type]
JobKind = Literal[tuple(k.value for k in JobKindEnum)]  # type: ignore[valid-type]
MAX_POINTS = 200_000
MAX_OFFSET = 1_000_000_000  # list offsets (SQLite integers overflow past 2**63)
MAX_ID_LENGTH = 64  # ids are 20 characters; room for the rig alias `default` and more
# A plan from the builder has at most 122 frames with a preset and 1666 in an extreme
# full-control case (64 steps, 13 periods per axis); a frame has 7 keys.
MAX_PLAN_FRAMES = 10_000
MAX_PLAN_KEYS = 64  # format, screen, frames and the plan's own metadata
MAX_FRAME_KEYS = 16
MAX_PLAN_NODES = 200_000  # keys and values in the whole plan
MAX_RIG_CONFIG_KEYS = 32  # a rig config has about 10 sections
MAX_RIG_CONFIG_NODES = 2_000
MAX_TREE_DEPTH = 8  # a plan nests 4 deep, a rig config 3
MAX_TREE_STRING = 4096  # names, device ids and paths in free-form documents
# Numbers in request bodies are typed strictly: `false` or "1" is not a number, NaN and
# infinities are refused (JSON has none, but Python's parser accepts NaN/Infinity).
Num = Annotated[float, Field(strict=True, allow_inf_nan=False)]
Coord = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-1e9, le=1e9)]
PoseStatus = Literal[
    "pending", "capturing", "decoding", "ready", "flagged", "failed", "cancelled", "interrupted"
]


def check_tree(value: Any, where: str, max_nodes: int, max_depth: int = MAX_TREE_DEPTH,
               max_string: int = MAX_TREE_STRING) -> None:
    """Raise ValueError if a free-form JSON document has more than `max_nodes` keys and
    values, nests deeper than `max_depth` or holds a string longer than `max_string`
    (whatever a request may carry is bounded before any code walks it recursively)."""
    nodes = 0
    todo: list[tuple[Any, int]] = [(value, 0)]
    while todo:
        item, depth = todo.pop()
        nodes += 1
        if nodes > max_nodes:
            raise ValueError(f"{where}: more than {max_nodes} keys and values")
        if depth > max_depth:
            raise ValueError(f"{where}: nested more than {max_depth} levels deep")
        if isinstance(item, str) and len(item) > max_string:
            raise ValueError(f"{where}: a string of {len(item)} characters "
                             f"(at most {max_string})")
        if isinstance(item, dict):
            nodes += len(item)  # the keys
            longest = max(map(len, item), default=0)
            if longest > max_string:
                raise ValueError(f"{where}: a key of {longest} characters (at most {max_string})")
            todo.extend((v, depth + 1) for v in item.values())
        elif isinstance(item, list):
            todo.extend((v, depth + 1) for v in item)


def _check_plan(plan: dict[str, Any]) -> dict[str, Any]:
    """Bound a plan document's size (its meaning is checked by `plan_from_dict`)."""
    frames = plan.get("frames")
    if isinstance(frames, list):
        if len(frames) > MAX_PLAN_FRAMES:
            raise ValueError(f"frames: {len(frames)} frames (at most {MAX_PLAN_FRAMES})")
        for i, frame in enumerate(frames):
            if isinstance(frame, dict) and len(frame) > MAX_FRAME_KEYS:
                raise ValueError(f"frames[{i}]: {len(frame)} keys (at most {MAX_FRAME_KEYS})")
    check_tree(plan, "plan", MAX_PLAN_NODES)
    return plan


def _check_rig_config(config: dict[str, Any]) -> dict[str, Any]:
    """Bound a rig config's size (its meaning is checked by `parse_rig_config`)."""
    check_tree(config, "config", MAX_RIG_CONFIG_NODES)
    return config


# The frame count is stated in words, not as maxItems: a schema fuzzer would answer a
# maxItems of 10,000 with megabytes of frames, which the body limits refuse with a 413.
PlanDocument = Annotated[dict[str, Any], Field(
    max_length=MAX_PLAN_KEYS,
    json_schema_extra={"properties": {"frames": {
        "type": "array", "description": f"at most {MAX_PLAN_FRAMES} frames",
        "items": {"type": "object", "maxProperties": MAX_FRAME_KEYS}}}},
), AfterValidator(_check_plan)]
RigConfigDocument = Annotated[dict[str, Any], Field(max_length=MAX_RIG_CONFIG_KEYS),
                              AfterValidator(_check_rig_config)]
IdStr = Annotated[str, Field(max_length=MAX_ID_LENGTH)]


def strict_config(*examples: dict[str, Any]) -> ConfigDict:
    """The model config of every request body: unknown fields are refused (422), and the
    OpenAPI document carries `examples`."""
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
    config: RigConfigDocument = Field(
        description=f"at most {MAX_RIG_CONFIG_NODES} keys and values, {MAX_TREE_DEPTH} levels")


class Rig(BaseModel):
    """A rig: display, camera, screen geometry and settings."""

    id: str
    name: str
    config: dict[str, Any]
    simulated: bool
    created_at: float


class CameraSettingsModel(BaseModel):
    """Camera settings to read or change."""

    model_config = strict_config(
        {"exposure_s": 0.01, "gain_db": 0.0, "pixel_format": "Mono8"}
    )
    exposure_s: Num | None = Field(default=None, gt=0, le=10)
    gain_db: Num | None = Field(default=None, ge=0, le=48)
    pixel_format: str | None = Field(default=None, min_length=1, max_length=32)


class ScreenPoseIn(BaseModel):
    """Where the simulated screen is: X_cam = R S + t; R from a rotation vector (Rodrigues)."""

    model_config = strict_config(
        {"rvec": [0.1, -0.05, 0.0], "tvec_mm": [-130.0, -100.0, 320.0]}
    )
    rvec: list[Annotated[Num, Field(ge=-10, le=10)]] = Field(
        min_length=3, max_length=3, description="rotation vector, radians")
    tvec_mm: list[Annotated[Num, Field(ge=-1e6, le=1e6)]] = Field(
        min_length=3, max_length=3, description="translation, mm")


class SessionCreate(BaseModel):
    """A session on a rig with a plan (given, or built from a preset for the rig's screen)."""

    model_config = strict_config(
        {"name": "lab-1", "preset": "fast"}
    )
    name: str = Field(default="", max_length=200)
    rig_id: IdStr | None = Field(default=None, description="default: the server's rig")
    plan: PlanDocument | None = Field(
        default=None, description=f"a phasecal.plan/1 document (at most {MAX_PLAN_FRAMES} "
        f"frames, {MAX_PLAN_NODES} keys and values, {MAX_TREE_DEPTH} levels)")
    preset: str | None = Field(default=None, max_length=32,
                               description="plan preset when no plan is given")


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

    model_config = strict_config(
        {"screen_pose": {"rvec": [0.1, 0.0, 0.0], "tvec_mm": [-130.0, -100.0, 320.0]}}
    )
    screen_pose: ScreenPoseIn | None = None
    noise_dn: float | None = Field(
        None, gt=0, le=1e4,
        description="per-frame camera noise sigma in DN; default: estimated from the residuals",
    )


class PoseCamera(BaseModel):
    """One camera of a pose captured on a rig of several cameras."""

    name: str
    status: PoseStatus
    valid_pixels: int | None = None
    width: int | None = None
    height: int | None = None
    error: str | None = None


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
    cameras: list[PoseCamera] | None = Field(
        None, description="a rig of several cameras: each one's maps (GET .../maps.npz"
        "?camera=NAME), the reference first; null for one camera")


class _CalibrationFields(BaseModel):
    """What every model's calibration request has besides its model and options."""

    model_config = ConfigDict(extra="forbid")
    pose_ids: list[IdStr] | None = Field(default=None, max_length=500)
    heldout_pose_ids: list[IdStr] = Field(default_factory=list, max_length=500)


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

    model_config = strict_config({"method": "rectangle", "source": "flats"},
                           {"method": "rotation", "source": "maps",
                            "pose_ids": ["pose_0123456789abcdef"]})
    method: Literal["rectangle", "selfcal", "rotation"]
    source: Literal["flats", "maps"] = "flats"
    pose_ids: list[IdStr] | None = Field(default=None, max_length=500)
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

    model_config = strict_config(
        {"points": [[0.0, 0.0, 1000.0], [100.0, 50.0, 800.0]]}
    )
    # fail_fast: one error for a bad row, not one per row (200,000 errors need ~300 MB)
    points: list[tuple[Coord, Coord, Coord]] = Field(max_length=MAX_POINTS, fail_fast=True)


class ProjectResponse(BaseModel):
    """Pixels (u, v); null rows where the model cannot see the point."""

    pixels: list[list[float | None]]


class UnprojectRequest(BaseModel):
    """Camera pixels (u, v)."""

    model_config = strict_config(
        {"pixels": [[320.0, 240.0], [10.5, 20.25]]}
    )
    pixels: list[tuple[Coord, Coord]] = Field(max_length=MAX_POINTS, fail_fast=True)


class UnprojectResponse(BaseModel):
    """Ray origins (mm) and unit directions; null rows where the model is not defined."""

    origins: list[list[float | None]]
    directions: list[list[float | None]]


class RigCalibrationCreate(BaseModel):
    """Calibrate every camera of a several-camera session's poses jointly (docs/rigs.md): each
    pose is a view all its cameras share; the result is a rig model (phasecal.rig/1)."""

    model_config = strict_config({"model": "opencv5"},
                                 {"model": "opencv5", "camera_models": {"right": "fisheye"},
                                  "options": {"max_points_per_view": 2000}})
    model: ModelName = Field(description="every camera's model unless camera_models names one")
    camera_models: dict[IdStr, ModelName] = Field(default_factory=dict, max_length=64)
    pose_ids: list[IdStr] | None = Field(default=None, max_length=500)
    heldout_pose_ids: list[IdStr] = Field(default_factory=list, max_length=500)
    reference: IdStr | None = Field(default=None, description="default: the poses' first camera")
    options: dict[IdStr, Any] = Field(
        default_factory=dict, max_length=64,
        description="the joint fit's options (max_points_per_view, outlier_sigmas, "
                    "max_iterations, seed) and every camera's model options")
