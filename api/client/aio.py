"""The asyncio phasecal client (httpx.AsyncClient): the same methods as `PhasecalClient`,
awaitable; job waits follow the SSE stream and cancel the server job if the task is
cancelled."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import tempfile
import time
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any, Concatenate, ParamSpec, TypeVar

import httpx

from api.client import ops
from api.client import types as t
from api.client.errors import ServiceError, job_error, raise_for_problem
from api.client.sync import CHUNK, RETRY_STATUS, SSE_READ_TIMEOUT_S

P = ParamSpec("P")
T = TypeVar("T")


def _method(build: Callable[P, ops.Op[T]]
            ) -> Callable[Concatenate[AsyncPhasecalClient, P], Awaitable[T]]:
    """An async client method running the operation `build` describes (same signature)."""

    async def method(self: AsyncPhasecalClient, *args: P.args, **kwargs: P.kwargs) -> T:
        return await self.run(build(*args, **kwargs))

    method.__doc__, method.__name__ = build.__doc__, build.__name__
    return method


class AsyncPhasecalClient:
    """Calls the REST API. Every POST carries an Idempotency-Key; requests are retried (same
    key) on transport errors and 502/503/504, up to `retries` times with backoff."""

    def __init__(self, base_url: str, token: str | None = None, timeout_s: float = 60.0,
                 retries: int = 2, transport: httpx.AsyncBaseTransport | None = None) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.AsyncClient(base_url=base_url, headers=headers, timeout=timeout_s,
                                 transport=transport)
        self.retries = retries

    async def close(self) -> None:
        """Close the connection pool."""
        await self.http.aclose()

    async def __aenter__(self) -> AsyncPhasecalClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- transport ------------------------------------------------------------------------
    async def _send(self, method: str, path: str, *, stream: bool = False,
              upload: ops.Opener | None = None, **kwargs: Any) -> httpx.Response:
        headers = dict(kwargs.pop("headers", None) or {})
        if method == "POST":
            headers.setdefault("Idempotency-Key", uuid.uuid4().hex)
        for attempt in range(self.retries + 1):
            handles: list[Any] = []
            try:
                if upload is not None:
                    kwargs["files"], handles = upload()
                req = self.http.build_request(method, path, headers=headers, **kwargs)
                r = await self.http.send(req, stream=stream)
            except httpx.TransportError:
                if attempt == self.retries:
                    raise
            else:
                if r.status_code not in RETRY_STATUS or attempt == self.retries:
                    if r.status_code >= 400:
                        await r.aread()
                        await r.aclose()
                        raise_for_problem(r)
                    return r
                await r.aclose()
            finally:
                for fh in handles:
                    fh.close()
            await asyncio.sleep(0.2 * 2**attempt)
        raise AssertionError("unreachable")

    async def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """Send a request (retried as above); `ServiceError` with the problem on 4xx/5xx."""
        return await self._send(method, path, **kwargs)

    async def run(self, op: ops.Op[T]) -> T:
        """Run an operation description and return its JSON answer."""
        return (await self._send(op.method, op.path, json=op.json, params=op.params)).json()

    async def get(self, path: str, **params: Any) -> Any:
        """GET returning JSON."""
        return (await self.request("GET", path, params=params or None)).json()

    async def post(self, path: str, body: dict[str, Any] | None = None) -> Any:
        """POST JSON returning JSON."""
        return (await self.request("POST", path, json=body or {})).json()

    # -- resources (api.client.ops) -----------------------------------------------------------
    health = _method(ops.health)
    list_devices = _method(ops.list_devices)
    list_rigs = _method(ops.list_rigs)
    create_rig = _method(ops.create_rig)
    get_rig = _method(ops.get_rig)
    move_screen = _method(ops.move_screen)
    camera_settings = _method(ops.camera_settings)
    create_session = _method(ops.create_session)
    list_sessions = _method(ops.list_sessions)
    get_session = _method(ops.get_session)
    get_plan = _method(ops.get_plan)
    capture_pose = _method(ops.capture_pose)
    resume_pose = _method(ops.resume_pose)
    list_poses = _method(ops.list_poses)
    get_pose = _method(ops.get_pose)
    calibrate = _method(ops.calibrate)
    quick_intrinsics = _method(ops.quick_intrinsics)
    get_intrinsics = _method(ops.get_intrinsics)
    list_calibrations = _method(ops.list_calibrations)
    get_calibration = _method(ops.get_calibration)
    project = _method(ops.project)
    unproject = _method(ops.unproject)
    undistort_points = _method(ops.undistort_points)
    create_batch = _method(ops.create_batch)
    get_job = _method(ops.get_job)
    list_jobs = _method(ops.list_jobs)
    cancel_job = _method(ops.cancel_job)

    # -- streamed uploads -------------------------------------------------------------------
    async def import_frames(self, session: str | t.Session, paths: list[Path],
                      noise_dn: float | None = None) -> t.Job:
        """Upload a `.npy` stack or frame images (streamed from disk) as a pose; the decode job."""
        data = {"noise_dn": str(noise_dn)} if noise_dn is not None else None
        r = await self._send("POST", f"/sessions/{ops.ident(session)}/poses/import",
                             upload=ops.upload_files("files", paths), data=data)
        return r.json()

    async def import_maps(self, session: str | t.Session, path: Path) -> t.Pose:
        """Upload a decoded maps NPZ (streamed) as a ready pose."""
        r = await self._send("POST", f"/sessions/{ops.ident(session)}/poses/import-maps",
                             upload=ops.upload_files("file", [path]))
        return r.json()

    # -- streamed downloads ---------------------------------------------------------------
    async def download(self, path: str, dest: str | Path, params: dict[str, Any] | None = None
                 ) -> httpx.Headers:
        """Stream a GET to `dest` (written under a temporary name, then renamed); its headers."""
        out = Path(dest)
        r = await self._send("GET", path, params=params, stream=True)
        fd, tmp = tempfile.mkstemp(prefix=out.name + ".", suffix=".part", dir=out.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                async for chunk in r.aiter_bytes(CHUNK):
                    fh.write(chunk)
            os.replace(tmp, out)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        finally:
            await r.aclose()
        return r.headers

    async def download_file(self, cal: str | t.Calibration, name: str, dest: str | Path) -> Path:
        """A stored calibration file (model.json, result.json, residuals.png, ...) to `dest`."""
        await self.download(ops.file_path(cal, name), dest)
        return Path(dest)

    async def download_maps(self, session: str | t.Session, pose: str | t.Pose,
                      dest: str | Path) -> Path:
        """A pose's decoded maps NPZ to `dest`."""
        await self.download(ops.maps_path(session, pose), dest)
        return Path(dest)

    async def download_frames(self, session: str | t.Session, pose: str | t.Pose,
                              dest: str | Path, image_format: str = "png") -> Path:
        """A pose's captured frames as a zip of frame_NNNN.png (or .tif) images to `dest`."""
        await self.download(ops.frames_zip_path(session, pose), dest,
                            params={"format": image_format})
        return Path(dest)

    async def export(self, cal: str | t.Calibration, fmt: str, dest: str | Path,
               **params: Any) -> dict[str, Any]:
        """`GET /calibrations/{id}/export` to `dest`; returns the export info (exact, residual)."""
        path, query = ops.export_request(cal, fmt, **params)
        headers = await self.download(path, dest, params=query)
        return json.loads(headers.get("phasecal-export-info", "{}"))

    # -- jobs -------------------------------------------------------------------------------
    async def events(self, job: str | t.Job) -> AsyncIterator[tuple[str, dict[str, Any]]]:
        """The job's server-sent events (`progress`..., `end`; keepalives included)."""
        timeout = httpx.Timeout(self.http.timeout.connect, read=SSE_READ_TIMEOUT_S)
        r = await self._send("GET", ops.job_events_path(job), stream=True, timeout=timeout)
        decoder = ops.SSEDecoder()
        try:
            async for line in r.aiter_lines():
                ev = decoder.feed(line)
                if ev is not None:
                    yield ev
        finally:
            await r.aclose()

    async def wait(self, job: str | t.Job | dict[str, Any], timeout_s: float = 600.0,
             check: bool = True, on_progress: Callable[[t.Job], None] | None = None) -> t.Job:
        """Follow the job's SSE stream to its end; its final state.

        `check`: raise `JobFailed` (`JobCancelled`) with the problem details unless it
        succeeded. If the waiting task is cancelled, the job is cancelled on the server.
        Reconnects if the stream drops; `TimeoutError` after `timeout_s`.
        """
        jid = ops.job_id(job)
        deadline = time.monotonic() + timeout_s
        try:
            final = await self._follow(jid, deadline, on_progress)
        except asyncio.CancelledError:
            with contextlib.suppress(ServiceError, httpx.HTTPError):
                await asyncio.shield(self.cancel_job(jid))
            raise
        if check and final["status"] != "succeeded":
            raise job_error(final)
        return final

    async def _follow(self, jid: str, deadline: float,
                on_progress: Callable[[t.Job], None] | None) -> t.Job:
        while True:
            try:
                async for event, data in self.events(jid):
                    if event == "end":
                        return data  # type: ignore[return-value]
                    if event == "progress" and on_progress is not None:
                        on_progress(data)  # type: ignore[arg-type]
                    if time.monotonic() > deadline:
                        break
            except httpx.TransportError:
                pass  # stream dropped: look at the job, then reconnect
            state = await self.get_job(jid)
            if state["status"] in t.TERMINAL:
                return state
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {jid} still {state['status']} at the deadline")
            await asyncio.sleep(0.2)
