"""Typed views of the service's JSON answers (plain dicts at run time; api.schemas is the
server's definition and tests/api/test_client.py checks that these keys match it)."""

from __future__ import annotations

from typing import Any, Literal, TypedDict

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled", "interrupted"]
TERMINAL: tuple[str, ...] = ("succeeded", "failed", "cancelled", "interrupted")


class Job(TypedDict):
    """A long operation (capture, decode, calibrate, batch) and its progress."""

    id: str
    kind: str
    status: JobStatus
    stage: str
    done: int
    total: int
    eta_s: float | None
    resource: str | None
    session_id: str | None
    error: str | None
    result: dict[str, Any] | None
    created_at: float
    started_at: float | None
    finished_at: float | None


class JobPage(TypedDict):
    """One page of jobs, newest first."""

    items: list[Job]
    total: int
    limit: int
    offset: int


class Rig(TypedDict):
    """A rig: display, camera, screen geometry and settings."""

    id: str
    name: str
    config: dict[str, Any]
    simulated: bool
    created_at: float


class Session(TypedDict):
    """A session: rig + pattern plan + poses."""

    id: str
    name: str
    rig_id: str | None
    frame_count: int
    plan_digest: str
    created_at: float


class Pose(TypedDict):
    """One pose: captured or imported frames and their decoded maps."""

    id: str
    session_id: str
    index: int
    source: str
    status: str
    job_id: str | None
    valid_pixels: int | None
    width: int | None
    height: int | None
    frames_done: int
    screen_pose: dict[str, Any] | None
    error: str | None
    created_at: float
    cameras: list[dict[str, Any]] | None  # a pose of several cameras: each one's status


class Calibration(TypedDict):
    """A calibration and, once it succeeded, its statistics and stored files."""

    id: str
    session_id: str
    model: str
    pose_ids: list[str]
    heldout_pose_ids: list[str]
    status: str
    job_id: str | None
    stats: dict[str, Any] | None
    exports: list[str]
    error: str | None
    created_at: float


class Problem(TypedDict, total=False):
    """RFC 9457 problem details (extra members allowed)."""

    type: str
    title: str
    status: int
    detail: str
    instance: str
