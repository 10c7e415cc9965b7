"""Typed Python client of the phasecal REST API, sync (`PhasecalClient`) and asyncio
(`AsyncPhasecalClient`), shipped with phasecal (docs/client.md)."""

from api.client.aio import AsyncPhasecalClient
from api.client.errors import JobCancelled, JobFailed, ServiceError
from api.client.sync import PhasecalClient
from api.client.types import TERMINAL, Calibration, Job, Pose, Rig, Session

__all__ = [
           "TERMINAL",
           "AsyncPhasecalClient",
           "Calibration",
           "Job",
           "JobCancelled",
           "JobFailed",
           "PhasecalClient",
           "Pose",
           "Rig",
           "ServiceError",
           "Session",
]
