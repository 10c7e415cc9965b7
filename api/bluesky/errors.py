"""What a phasecal device raises when the service refuses a request or a job does not
succeed: the device, what it was doing and the service's own reason in one message."""

from __future__ import annotations

from api.client import ServiceError
from api.client.types import Problem


class PhasecalDeviceError(RuntimeError):
    """A request of a phasecal device failed (`status`, `problem`: the service's problem
    details, when it answered) or its job ended failed, cancelled or interrupted."""

    def __init__(self, message: str, status: int | None = None,
                 problem: Problem | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.problem: Problem = problem or {}

    @classmethod
    def from_service(cls, device: str, action: str, exc: ServiceError) -> PhasecalDeviceError:
        """`device`: `action` failed, with the service's status, problem type and detail."""
        kind = exc.type.rsplit("/", 1)[-1]
        return cls(f"{device}: {action} failed: {exc.detail} (HTTP {exc.status} {kind})",
                   exc.status, exc.problem)
