"""ophyd-async devices for a phasecal rig, driving a running phasecal service over its REST
API with the project's asyncio client, so a Bluesky RunEngine treats phasecal like any other
detector: `PhasecalScreen` (the simulated screen's pose, settable), `PhasecalCapture` (trigger
= capture and decode one pose), `PhasecalGuide` (the next screen pose the service suggests)
and `PhasecalCalibration` (trigger = fit a model to the captured poses).

A device's job is cancelled on the server when the device is stopped, paused or unstaged
while the job runs (a RunEngine paused, stopped or aborted mid-capture), so no capture
outlives the plan and a paused run leaves the rig free."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator, Awaitable, Mapping, Sequence
from typing import Any

import numpy as np
from ophyd_async.core import (
    Array1D,
    AsyncStatus,
    StandardReadable,
    StandardReadableFormat,
    soft_signal_r_and_setter,
    soft_signal_rw,
)

from api.bluesky.errors import PhasecalDeviceError
from api.client import AsyncPhasecalClient, ServiceError
from api.client import types as t
from api.client.ops import maps_path

ScreenPose = Mapping[str, Sequence[float]]  # {"rvec": rad (3), "tvec_mm": mm (3)}
Format = StandardReadableFormat


def screen_pose_vectors(pose: ScreenPose) -> tuple[list[float], list[float]]:
    """(rvec, tvec_mm) of a screen pose as the service takes it; ValueError naming the field
    when one is missing or is not three numbers."""
    out = []
    for key in ("rvec", "tvec_mm"):
        if key not in pose:
            raise ValueError(f"screen pose: missing {key!r} (expected rvec and tvec_mm)")
        values = np.asarray(pose[key], dtype=float).ravel()
        if values.shape != (3,) or not np.all(np.isfinite(values)):
            raise ValueError(f"screen pose: {key} must be 3 finite numbers, got {pose[key]!r}")
        out.append(values.tolist())
    return out[0], out[1]


@contextlib.asynccontextmanager
async def service_errors(device: str, action: str) -> AsyncIterator[None]:
    """Turn the service's refusal of `action` into a `PhasecalDeviceError` with its reason."""
    try:
        yield
    except ServiceError as exc:
        raise PhasecalDeviceError.from_service(device, action, exc) from exc


class ServiceJob:
    """The one job a device runs at a time: started, followed to its end, and cancelled on
    the server when the device is stopped, when the waiting task is cancelled, or when it
    has not ended within `timeout_s`. A stop that comes while the job is being created
    cancels it as soon as its id is known."""

    def __init__(self, client: AsyncPhasecalClient, timeout_s: float) -> None:
        self.client = client
        self.timeout_s = timeout_s
        self.job_id: str | None = None
        self.ended: asyncio.Event | None = None
        self.stopped = False  # the device asked the running job to stop

    async def run(self, start: Awaitable[t.Job]) -> t.Job:
        """Start the job (awaiting `start`) and follow it to its end; its final state,
        whatever it is."""
        self.stopped = False
        self.ended = asyncio.Event()
        try:
            job = await start
            self.job_id = job["id"]
            if self.stopped:
                await self.cancel_on_server()
            try:
                return await self.client.wait(job, timeout_s=self.timeout_s, check=False)
            except TimeoutError:
                await self.cancel_on_server()
                raise PhasecalDeviceError(
                    f"job {job['id']} ({job['kind']}) did not end within {self.timeout_s:g} s; "
                    "it was cancelled on the service") from None
        finally:
            self.job_id = None
            self.ended.set()

    async def stop(self) -> None:
        """Cancel the running job on the server and wait until its follower has seen it end
        (it ends `cancelled`); nothing when no job runs."""
        ended = self.ended
        if ended is None or ended.is_set():
            return
        self.stopped = True
        if self.job_id is not None:
            await self.cancel_on_server()
        await ended.wait()

    async def cancel_on_server(self) -> None:
        """`POST /jobs/{id}/cancel`; a job that ended meanwhile (409) needs nothing."""
        try:
            await self.client.cancel_job(str(self.job_id))
        except ServiceError as exc:
            if exc.status != 409:
                raise


def resource_id(job: t.Job) -> str:
    """The id of the pose or calibration a job produces (the last part of its resource)."""
    return str(job["resource"]).rsplit("/", 1)[-1]


class PhasecalScreen(StandardReadable):
    """The simulated rig's screen pose as a movable: `set({"rvec": ..., "tvec_mm": ...})`
    moves it (`PUT /rigs/{id}/screen-pose`); reads the pose last set. A real rig refuses
    with the service's reason (409)."""

    def __init__(self, client: AsyncPhasecalClient, rig_id: str = "default",
                 name: str = "") -> None:
        self.client = client
        self.rig_id = rig_id
        with self.add_children_as_readables(Format.HINTED_UNCACHED_SIGNAL):
            self.rvec, self._set_rvec = soft_signal_r_and_setter(Array1D[np.float64],
                                                                 units="rad")
            self.tvec_mm, self._set_tvec = soft_signal_r_and_setter(Array1D[np.float64],
                                                                    units="mm")
        with self.add_children_as_readables(Format.CONFIG_SIGNAL):
            self.rig, set_rig = soft_signal_r_and_setter(str)
        set_rig(rig_id)
        super().__init__(name=name)

    @AsyncStatus.wrap
    async def set(self, value: ScreenPose) -> None:
        """Move the screen to `value` (rvec rad, tvec_mm mm: X_cam = R S + t)."""
        rvec, tvec = screen_pose_vectors(value)
        async with service_errors(self.name, f"moving the screen of rig {self.rig_id}"):
            await self.client.move_screen(self.rig_id, rvec, tvec)
        self._set_rvec(np.asarray(rvec))
        self._set_tvec(np.asarray(tvec))


class PhasecalCapture(StandardReadable):
    """A phasecal session's capture as a triggerable detector.

    `stage()` attaches to `session_id` or creates a session on `rig_id` (with `preset` or
    `plan`); `trigger()` captures and decodes one pose on it; the reading is the pose's id,
    status, valid-pixel count and the URL of its decoded maps. `stop()`, `pause()` and
    `unstage()` cancel a capture in progress on the server; that trigger then completes with
    the pose `cancelled` (any other capture that does not succeed fails the trigger with the
    service's reason)."""

    def __init__(self, client: AsyncPhasecalClient, rig_id: str = "default",
                 session_id: str | None = None, session_name: str = "",
                 preset: str | None = None, plan: dict[str, Any] | None = None,
                 capture_timeout_s: float = 600.0, name: str = "") -> None:
        self.client = client
        self.rig_id = rig_id
        self.attach_to = session_id
        self.session_name = session_name
        self.preset = preset
        self.plan = plan
        self.job = ServiceJob(client, capture_timeout_s)
        with self.add_children_as_readables(Format.UNCACHED_SIGNAL):
            self.pose_id, self._set_pose_id = soft_signal_r_and_setter(str)
            self.status, self._set_status = soft_signal_r_and_setter(str)
            self.maps_url, self._set_maps_url = soft_signal_r_and_setter(str)
        with self.add_children_as_readables(Format.HINTED_UNCACHED_SIGNAL):
            self.valid_pixels, self._set_valid = soft_signal_r_and_setter(int, units="px")
        with self.add_children_as_readables(Format.CONFIG_SIGNAL):
            self.session_id, self._set_session = soft_signal_r_and_setter(str)
            self.frame_count, self._set_frame_count = soft_signal_r_and_setter(int)
        super().__init__(name=name)

    @AsyncStatus.wrap
    async def stage(self) -> None:
        """Attach to the given session, or create one for this run."""
        if self.attach_to is not None:
            async with service_errors(self.name, f"attaching to session {self.attach_to}"):
                session = await self.client.get_session(self.attach_to)
        else:
            async with service_errors(self.name, f"creating a session on rig {self.rig_id}"):
                session = await self.client.create_session(
                    self.session_name, rig_id=self.rig_id, preset=self.preset, plan=self.plan)
        self._set_session(session["id"])
        self._set_frame_count(session["frame_count"])
        await super().stage()

    @AsyncStatus.wrap
    async def unstage(self) -> None:
        """Cancel a capture still running; the session and its poses stay on the service."""
        await self.job.stop()
        await super().unstage()

    async def stop(self, success: bool = True) -> None:
        """Cancel a capture in progress (its job ends `cancelled` on the server)."""
        await self.job.stop()

    async def pause(self) -> None:
        """The RunEngine pauses: cancel a capture in progress so the rig is free meanwhile;
        on resume the run goes back to its checkpoint and captures that pose again."""
        await self.job.stop()

    async def resume(self) -> None:
        """Nothing to restore: a paused capture was cancelled and is captured afresh."""

    @AsyncStatus.wrap
    async def trigger(self) -> None:
        """Capture one pose at the screen's current pose and wait for its maps."""
        session = await self.session_id.get_value()
        if not session:
            raise PhasecalDeviceError(f"{self.name}: stage the device (or run it in a plan "
                                      "that stages it) before triggering: no session yet")
        async with service_errors(self.name, f"capturing a pose on session {session}"):
            final = await self.job.run(self.client.capture_pose(session))
            pose = await self.client.get_pose(session, resource_id(final))
        if final["status"] != "succeeded" and not self.job.stopped:
            raise PhasecalDeviceError(
                f"{self.name}: capture of pose {pose['id']} on session {session} ended "
                f"{final['status']}: {final.get('error') or pose.get('error') or 'no reason'}")
        self._set_pose_id(pose["id"])
        self._set_status(pose["status"])
        self._set_valid(int(pose["valid_pixels"] or 0))
        self._set_maps_url(str(self.client.http.base_url.join(maps_path(session, pose))))


DECODED = ("ready", "flagged")  # pose statuses whose maps a fit can use


class PhasecalGuide(StandardReadable):
    """Where to put the screen next, as the service plans it for `capture`'s session.

    A trigger reads one suggestion: first, in turn, the poses of
    `GET /sessions/{id}/starting-poses` (`starting_count` planned from the rig alone at the
    first trigger after staging, less those a decoded pose already matches), then
    `GET /sessions/{id}/next-pose` for `model` (the pose that most lowers the worst
    predicted ray uncertainty). The suggestion moves on only when the session has one more
    decoded pose, so triggering again after a cancelled capture (a resumed run going back to
    its checkpoint) suggests the same pose. The reading is the suggested `rvec`/`tvec_mm`,
    its placement in words, where it came from, and the predicted worst ray sigma after it
    (NaN for a starting pose)."""

    def __init__(self, capture: PhasecalCapture, model: str = "opencv-rational",
                 starting_count: int = 5, name: str = "") -> None:
        # the capture's session and client (not `capture` itself: that would make it a child)
        self.current_session = capture.session_id.get_value
        self.client = capture.client
        self.model = model
        self.starting_count = starting_count
        self.starting: list[dict[str, Any]] | None = None  # planned at the first trigger
        self.decoded_at_start = 0  # the session's decoded poses when they were planned
        with self.add_children_as_readables(Format.UNCACHED_SIGNAL):
            self.rvec, self._set_rvec = soft_signal_r_and_setter(Array1D[np.float64],
                                                                 units="rad")
            self.tvec_mm, self._set_tvec = soft_signal_r_and_setter(Array1D[np.float64],
                                                                    units="mm")
            self.placement, self._set_placement = soft_signal_r_and_setter(str)
            self.source, self._set_source = soft_signal_r_and_setter(str)
            self.predicted_sigma_urad, self._set_sigma = soft_signal_r_and_setter(
                float, units="urad")
        super().__init__(name=name)

    @AsyncStatus.wrap
    async def stage(self) -> None:
        """Plan the starting poses afresh for this run."""
        self.starting = None
        await super().stage()

    async def decoded_poses(self, session: str) -> int:
        """How many of the session's poses are decoded."""
        async with service_errors(self.name, f"listing the poses of session {session}"):
            poses = await self.client.list_poses(session)
        return sum(p["status"] in DECODED for p in poses)

    @AsyncStatus.wrap
    async def trigger(self) -> None:
        """Ask the service for the next screen pose."""
        session = await self.current_session()
        decoded = await self.decoded_poses(session)
        if self.starting is None:
            async with service_errors(self.name, f"planning starting poses of session {session}"):
                planned = await self.client.get(f"/sessions/{session}/starting-poses",
                                                count=self.starting_count)
            self.starting = [p for p in planned["poses"] if p["captured_by"] is None]
            self.decoded_at_start = decoded
        turn = decoded - self.decoded_at_start
        if turn < len(self.starting):
            item, source, sigma = self.starting[turn], "starting-poses", float("nan")
        else:
            async with service_errors(self.name, f"planning the next pose of session {session}"):
                item = await self.client.get(f"/sessions/{session}/next-pose", model=self.model)
            source = "next-pose"
            sigma = float(item["predicted_worst_ray_sigma_urad"]["after"])
        rvec, tvec = screen_pose_vectors(item["screen_pose"])
        self._set_rvec(np.asarray(rvec))
        self._set_tvec(np.asarray(tvec))
        self._set_placement(str(item["placement"]))
        self._set_source(source)
        self._set_sigma(sigma)


class PhasecalCalibration(StandardReadable):
    """A calibration of `capture`'s session as a triggerable detector.

    Its configuration signals say what to fit: `model`, `pose_ids` (empty: every ready pose)
    and `heldout_pose_ids`; `options` are the model's options. `trigger()` runs the job;
    the reading is the calibration id, its status, RMS reprojection error, held-out RMS,
    whether the fit converged, and every statistic as JSON (`stats`), so the run's
    documents carry the whole result. `stop()`, `pause()` and `unstage()` cancel a fit in
    progress (that trigger completes with the status `cancelled`)."""

    def __init__(self, capture: PhasecalCapture, model: str = "opencv5",
                 options: dict[str, Any] | None = None, fit_timeout_s: float = 1800.0,
                 name: str = "") -> None:
        # the capture's session and client (not `capture` itself: that would make it a child)
        self.current_session = capture.session_id.get_value
        self.client = capture.client
        self.options = options
        self.job = ServiceJob(capture.client, fit_timeout_s)
        with self.add_children_as_readables(Format.CONFIG_SIGNAL):
            self.model = soft_signal_rw(str, model)
            self.pose_ids = soft_signal_rw(Sequence[str], [])
            self.heldout_pose_ids = soft_signal_rw(Sequence[str], [])
        with self.add_children_as_readables(Format.UNCACHED_SIGNAL):
            self.calibration_id, self._set_id = soft_signal_r_and_setter(str)
            self.status, self._set_status = soft_signal_r_and_setter(str)
            self.converged, self._set_converged = soft_signal_r_and_setter(bool)
            self.heldout_rms_px, self._set_heldout = soft_signal_r_and_setter(float, units="px")
            self.stats, self._set_stats = soft_signal_r_and_setter(str)
        with self.add_children_as_readables(Format.HINTED_UNCACHED_SIGNAL):
            self.rms_px, self._set_rms = soft_signal_r_and_setter(float, units="px")
        super().__init__(name=name)

    @AsyncStatus.wrap
    async def unstage(self) -> None:
        """Cancel a fit still running."""
        await self.job.stop()
        await super().unstage()

    async def stop(self, success: bool = True) -> None:
        """Cancel a fit in progress (its job ends `cancelled` on the server)."""
        await self.job.stop()

    async def pause(self) -> None:
        """The RunEngine pauses: cancel a fit in progress; on resume it is fitted again."""
        await self.job.stop()

    async def resume(self) -> None:
        """Nothing to restore: a paused fit was cancelled and is run afresh."""

    @AsyncStatus.wrap
    async def trigger(self) -> None:
        """Fit the model and wait for its statistics."""
        session = await self.current_session()
        model, poses, heldout = await asyncio.gather(
            self.model.get_value(), self.pose_ids.get_value(),
            self.heldout_pose_ids.get_value())
        client = self.client
        async with service_errors(self.name, f"calibrating {model} on session {session}"):
            final = await self.job.run(client.calibrate(
                session, model, list(poses) or None, list(heldout) or None, self.options))
            cal = await client.get_calibration(resource_id(final))
        if final["status"] != "succeeded" and not self.job.stopped:
            raise PhasecalDeviceError(
                f"{self.name}: calibration {cal['id']} ({model}) on session {session} ended "
                f"{final['status']}: {final.get('error') or cal.get('error') or 'no reason'}")
        stats = cal["stats"] or {}
        heldout_stats = stats.get("heldout") or {}
        self._set_id(cal["id"])
        self._set_status(cal["status"])
        self._set_rms(float(stats.get("rms_px", float("nan"))))
        self._set_heldout(float(heldout_stats.get("rms_px", float("nan"))))
        self._set_converged(bool(stats.get("converged", False)))
        self._set_stats(json.dumps(stats, sort_keys=True))
