"""A small synchronous HTTP client for the phasecal service (rig scripts, demo, tests)."""

from __future__ import annotations

import time
import uuid
from pathlib import Path
from typing import Any

import httpx

TERMINAL = ("succeeded", "failed", "cancelled", "interrupted")


class ServiceError(RuntimeError):
    """A non-2xx answer; the message carries the problem+json detail."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(f"HTTP {status}: {detail}")
        self.status = status
        self.detail = detail


class PhasecalClient:
    """Calls the REST API; every POST carries a fresh Idempotency-Key and is retried once."""

    def __init__(self, base_url: str, token: str | None = None, timeout_s: float = 60.0) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=base_url, headers=headers, timeout=timeout_s)

    def close(self) -> None:
        """Close the connection pool."""
        self.http.close()

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """Send a request; raise `ServiceError` with the problem detail on 4xx/5xx."""
        if method == "POST":
            kwargs.setdefault("headers", {})["Idempotency-Key"] = uuid.uuid4().hex
            try:
                r = self.http.request(method, path, **kwargs)
            except httpx.TransportError:
                r = self.http.request(method, path, **kwargs)  # same key: safe retry
        else:
            r = self.http.request(method, path, **kwargs)
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text
            raise ServiceError(r.status_code, str(detail))
        return r

    def get(self, path: str, **params: Any) -> Any:
        """GET returning JSON."""
        return self.request("GET", path, params=params or None).json()

    def post(self, path: str, body: dict[str, Any] | None = None) -> Any:
        """POST JSON returning JSON."""
        return self.request("POST", path, json=body or {}).json()

    def wait(self, job: dict[str, Any] | str, timeout_s: float = 600.0,
             poll_s: float = 0.1) -> dict[str, Any]:
        """Poll a job until it ends; returns the final job (raises on timeout)."""
        job_id = job if isinstance(job, str) else job["id"]
        deadline = time.monotonic() + timeout_s
        while True:
            state = self.get(f"/jobs/{job_id}")
            if state["status"] in TERMINAL:
                return state
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {state['status']} after {timeout_s} s")
            time.sleep(poll_s)

    def import_frames(self, session_id: str, paths: list[Path],
                      noise_dn: float | None = None) -> dict[str, Any]:
        """Upload a `.npy` stack or frame images as a new pose; returns the decode job."""
        files = [("files", (p.name, p.read_bytes(), "application/octet-stream")) for p in paths]
        data = {"noise_dn": str(noise_dn)} if noise_dn is not None else None
        return self.request("POST", f"/sessions/{session_id}/poses/import", files=files,
                            data=data).json()
