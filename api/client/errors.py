"""Client errors carrying RFC 9457 problem details: failed requests and failed jobs."""

from __future__ import annotations

from typing import Any

import httpx

from api.client.types import Job, Problem

PROBLEM_BASE = "https://phasecal.dev/problems/"


class ServiceError(RuntimeError):
    """A request answered 4xx/5xx: `status`, `problem` (the problem+json document), `detail`."""

    def __init__(self, status: int, detail: str, problem: Problem | None = None) -> None:
        super().__init__(f"HTTP {status}: {detail}")
        self.status = status
        self.detail = detail
        self.problem: Problem = problem or {"status": status, "detail": detail}

    @property
    def type(self) -> str:
        """The problem type URI (e.g. .../problems/not-found), or about:blank."""
        return self.problem.get("type", "about:blank")


class JobFailed(ServiceError):
    """A job ended failed, cancelled or interrupted; `job` is its final state."""

    def __init__(self, job: Job) -> None:
        status = job["status"]
        detail = job.get("error") or f"job {job['id']} {status}"
        problem: Problem = {"type": PROBLEM_BASE + f"job-{status}", "title": f"Job {status}",
                            "status": 500 if status == "failed" else 409,
                            "detail": detail, "instance": f"/jobs/{job['id']}"}
        super().__init__(problem["status"], detail, problem)
        self.job = job
        self.job_status = status


class JobCancelled(JobFailed):
    """The job ended `cancelled` (by this client or another)."""


def job_error(job: Job) -> JobFailed:
    """The exception for a job that did not succeed."""
    return JobCancelled(job) if job["status"] == "cancelled" else JobFailed(job)


def raise_for_problem(r: httpx.Response) -> None:
    """Raise `ServiceError` with the parsed problem document for a 4xx/5xx answer."""
    if r.status_code < 400:
        return
    problem: dict[str, Any] = {}
    try:
        body = r.json()
        if isinstance(body, dict):
            problem = body
    except ValueError:
        pass
    detail = str(problem.get("detail") or r.text or r.reason_phrase)
    problem.setdefault("status", r.status_code)
    raise ServiceError(r.status_code, detail, problem)  # type: ignore[arg-type]
