"""One description per REST operation (method, path, body, how the answer is read), shared by
the sync and the async client so each resource is written once: `api.client.methods` makes
each builder here a method of both clients, `api.client.core` runs the descriptions."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar
from urllib.parse import quote

import httpx

from api.client import types as t
from api.client.errors import PROBLEM_BASE, ServiceError

T = TypeVar("T")
#: The collections whose calibrations have a report page (`{collection}/{id}/report.html`).
REPORT_COLLECTIONS = ("/calibrations", "/target-rig-calibrations")
#: Opens an upload's files afresh for each try: (httpx `files`, handles to close after it).
Opener = Callable[[], tuple[list[tuple[str, Any]], list[Any]]]


def json_body(r: httpx.Response) -> Any:
    """The answer of most operations: the response's JSON."""
    return r.json()


def whole_response(r: httpx.Response) -> httpx.Response:
    """The answer of `request`: the response itself."""
    return r


def response_headers(r: httpx.Response) -> httpx.Headers:
    """The answer of a plain download: the headers (the body went to the file)."""
    return r.headers


@dataclass(frozen=True)
class Op(Generic[T]):
    """A REST call: JSON body, form data, uploaded files or params in; its `answer` read from
    the response (JSON by default). With `save_to` the body is streamed into that file
    (written under a temporary name, then renamed); with `stream` it is left unread for the
    caller. `options` are further httpx request options (headers, content, timeout)."""

    method: str
    path: str
    json: Any = None
    params: dict[str, Any] | None = None
    ok: tuple[int, ...] = field(default=(200, 201, 202))
    data: dict[str, Any] | None = None
    upload: Opener | None = None
    save_to: Path | None = None
    stream: bool = False
    options: dict[str, Any] = field(default_factory=dict)
    answer: Callable[[httpx.Response], T] = json_body

    def request_options(self) -> dict[str, Any]:
        """Keyword arguments of `httpx.Client.build_request` (files excepted: an upload is
        opened afresh for each try)."""
        return {"json": self.json, "params": self.params, "data": self.data, **self.options}


def ident(value: str | Mapping[str, Any], key: str = "id") -> str:
    """An id given as a string or as the resource dict; URL-quoted."""
    raw = value[key] if isinstance(value, Mapping) else value
    return quote(str(raw), safe="")


def _drop_none(d: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in d.items() if v is not None}


# -- any request --------------------------------------------------------------------------------
def request(method: str, path: str, **options: Any) -> Op[httpx.Response]:
    """Send a request (retried as every call is); `ServiceError` with the problem on 4xx/5xx.
    `stream=True` leaves the body unread (the caller closes the response)."""
    stream = bool(options.pop("stream", False))
    return Op(method, path, stream=stream, upload=options.pop("upload", None), options=options,
              answer=whole_response)


def get(path: str, **params: Any) -> Op[Any]:
    """GET returning JSON."""
    return Op("GET", path, params=params or None)


def post(path: str, body: dict[str, Any] | None = None) -> Op[Any]:
    """POST JSON returning JSON."""
    return Op("POST", path, json=body or {})


# -- service, rigs ---------------------------------------------------------------------------
def health() -> Op[dict[str, Any]]:
    """Service liveness."""
    return Op("GET", "/health")


def list_devices() -> Op[list[dict[str, Any]]]:
    """Devices the server can see."""
    return Op("GET", "/devices")


def list_rigs() -> Op[list[t.Rig]]:
    """All rigs."""
    return Op("GET", "/rigs")


def create_rig(name: str, config: dict[str, Any]) -> Op[t.Rig]:
    """Register a rig configuration."""
    return Op("POST", "/rigs", json={"name": name, "config": config})


def get_rig(rig: str | t.Rig) -> Op[t.Rig]:
    """One rig."""
    return Op("GET", f"/rigs/{ident(rig)}")


def move_screen(rig: str | t.Rig, rvec: Sequence[float], tvec_mm: Sequence[float]
                ) -> Op[dict[str, Any]]:
    """Move a simulated rig's screen (X_cam = R S + t)."""
    return Op("PUT", f"/rigs/{ident(rig)}/screen-pose",
              json={"rvec": list(rvec), "tvec_mm": list(tvec_mm)})


def camera_settings(rig: str | t.Rig, **settings: Any) -> Op[dict[str, Any]]:
    """Read (no arguments) or change exposure_s / gain_db / pixel_format of a rig's camera."""
    if not settings:
        return Op("GET", f"/rigs/{ident(rig)}/camera/settings")
    return Op("PUT", f"/rigs/{ident(rig)}/camera/settings", json=settings)


# -- sessions, poses ----------------------------------------------------------------------
def create_session(name: str = "", rig_id: str | None = None, preset: str | None = None,
                   plan: dict[str, Any] | None = None) -> Op[t.Session]:
    """A session on a rig (default: the server's) with a plan or plan preset."""
    return Op("POST", "/sessions", json=_drop_none(
        {"name": name, "rig_id": rig_id, "preset": preset, "plan": plan}))


def list_sessions(limit: int = 100, offset: int = 0) -> Op[list[t.Session]]:
    """Sessions, newest first."""
    return Op("GET", "/sessions", params={"limit": limit, "offset": offset})


def get_session(session: str | t.Session) -> Op[t.Session]:
    """One session."""
    return Op("GET", f"/sessions/{ident(session)}")


def get_plan(session: str | t.Session) -> Op[dict[str, Any]]:
    """The session's phasecal.plan/1 document."""
    return Op("GET", f"/sessions/{ident(session)}/plan")


def capture_pose(session: str | t.Session, screen_pose: dict[str, Any] | None = None
                 ) -> Op[t.Job]:
    """Capture (and decode) one pose; returns the job."""
    body = {"screen_pose": screen_pose} if screen_pose is not None else {}
    return Op("POST", f"/sessions/{ident(session)}/poses", json=body)


def resume_pose(session: str | t.Session, pose: str | t.Pose) -> Op[t.Job]:
    """Resume an interrupted or cancelled capture."""
    return Op("POST", f"/sessions/{ident(session)}/poses/{ident(pose)}/resume", json={})


def list_poses(session: str | t.Session) -> Op[list[t.Pose]]:
    """The session's poses."""
    return Op("GET", f"/sessions/{ident(session)}/poses")


def get_pose(session: str | t.Session, pose: str | t.Pose) -> Op[t.Pose]:
    """One pose."""
    return Op("GET", f"/sessions/{ident(session)}/poses/{ident(pose)}")


# -- calibrations ---------------------------------------------------------------------------
def calibrate(session: str | t.Session, model: str, pose_ids: list[str] | None = None,
              heldout_pose_ids: list[str] | None = None,
              options: dict[str, Any] | None = None) -> Op[t.Job]:
    """Start a calibration job of `model` on the session's poses."""
    body = _drop_none({"model": model, "pose_ids": pose_ids,
                       "heldout_pose_ids": heldout_pose_ids, "options": options})
    return Op("POST", f"/sessions/{ident(session)}/calibrations", json=body)


def quick_intrinsics(session: str | t.Session, method: str, source: str = "flats",
                     pose_ids: list[str] | None = None, square_pixels: bool = False,
                     zero_skew: bool = False) -> Op[t.Job]:
    """Start a quick-intrinsics job (rectangle, selfcal, rotation) on white flats or maps."""
    body = _drop_none({"method": method, "source": source, "pose_ids": pose_ids,
                       "square_pixels": square_pixels, "zero_skew": zero_skew})
    return Op("POST", f"/sessions/{ident(session)}/intrinsics", json=body)


def get_intrinsics(session: str | t.Session) -> Op[dict[str, Any]]:
    """The session's latest quick-intrinsics result (phasecal.intrinsics/1)."""
    return Op("GET", f"/sessions/{ident(session)}/intrinsics")


def list_calibrations(session_id: str | None = None, limit: int = 100, offset: int = 0
                      ) -> Op[list[t.Calibration]]:
    """Calibrations, newest first, optionally of one session."""
    return Op("GET", "/calibrations",
              params=_drop_none({"session_id": session_id, "limit": limit, "offset": offset}))


def get_calibration(cal: str | t.Calibration) -> Op[t.Calibration]:
    """One calibration (statistics once it succeeded)."""
    return Op("GET", f"/calibrations/{ident(cal)}")


def calibrate_target_rig(cameras: Mapping[str, Mapping[str, Any]], model: str,
                         reference: str | None = None,
                         camera_models: Mapping[str, str] | None = None,
                         heldout_shots: list[str] | None = None,
                         options: dict[str, Any] | None = None) -> Op[t.Job]:
    """Start a rig calibration from target sessions: `cameras` maps each camera to
    `{"session_id": ..., "views": {shot: view id}}`; views of one shot are one placement."""
    body = _drop_none({"cameras": {k: dict(v) for k, v in cameras.items()}, "model": model,
                       "reference": reference,
                       "camera_models": None if camera_models is None else dict(camera_models),
                       "heldout_shots": heldout_shots, "options": options})
    return Op("POST", "/target-rig-calibrations", json=body)


def get_target_rig_calibration(cal: str | Mapping[str, Any]) -> Op[dict[str, Any]]:
    """A rig calibration from target sessions: its status and, once it succeeded, each
    camera's extrinsics with their sigma."""
    return Op("GET", f"/target-rig-calibrations/{ident(cal)}")


def export_target_rig(cal: str | Mapping[str, Any], fmt: str, dest: str | Path,
                      **params: Any) -> Op[dict[str, Any]]:
    """`GET /target-rig-calibrations/{id}/rig/export` (`camera=` or `cameras="A,B"`) to
    `dest`; returns the export info."""
    return Op("GET", f"/target-rig-calibrations/{ident(cal)}/rig/export",
              params={"format": fmt, **params}, save_to=Path(dest), answer=export_info)


def project(cal: str | t.Calibration, points: Iterable[Sequence[float]]) -> Op[dict[str, Any]]:
    """Camera-frame points (mm) -> `{"pixels": ...}` (None rows where unseen)."""
    return Op("POST", f"/calibrations/{ident(cal)}/project",
              json={"points": [list(map(float, p)) for p in points]})


def unproject(cal: str | t.Calibration, pixels: Iterable[Sequence[float]]) -> Op[dict[str, Any]]:
    """Pixels -> `{"origins": ..., "directions": ...}`."""
    return Op("POST", f"/calibrations/{ident(cal)}/unproject",
              json={"pixels": [list(map(float, p)) for p in pixels]})


def undistort_points(cal: str | t.Calibration, pixels: Iterable[Sequence[float]],
                     pinhole: Sequence[float] | None = None,
                     rotation: Sequence[float] | None = None,
                     align_to: str | None = None) -> Op[dict[str, Any]]:
    """Pixels -> virtual-pinhole pixels `{"pixels": ...}` (docs/exports.md)."""
    body = _drop_none({"pixels": [list(map(float, p)) for p in pixels],
                       "pinhole": None if pinhole is None else list(pinhole),
                       "rotation": None if rotation is None else list(rotation),
                       "align_to": align_to})
    return Op("POST", f"/calibrations/{ident(cal)}/undistort-points", json=body)


def create_batch(body: dict[str, Any]) -> Op[t.Job]:
    """Re-calibrate sessions x model settings as one job (docs/scaleout.md)."""
    return Op("POST", "/batches/calibrations", json=body)


# -- jobs ----------------------------------------------------------------------------------
def get_job(job: str | t.Job) -> Op[t.Job]:
    """One job's state."""
    return Op("GET", f"/jobs/{ident(job)}")


def list_jobs(status: str | None = None, kind: str | None = None,
              session_id: str | None = None, limit: int = 50, offset: int = 0
              ) -> Op[t.JobPage]:
    """Jobs, newest first, filtered."""
    return Op("GET", "/jobs", params=_drop_none({"status": status, "kind": kind,
                                                 "session_id": session_id, "limit": limit,
                                                 "offset": offset}))


def cancel_job(job: str | t.Job) -> Op[t.Job]:
    """Ask a queued/running job to stop (409 problem if it already ended)."""
    return Op("POST", f"/jobs/{ident(job)}/cancel", json={})


# -- paths of streamed transfers --------------------------------------------------------------
def file_path(cal: str | t.Calibration, name: str) -> str:
    """Path of a stored calibration file (model.json, result.json, residuals.png, ...)."""
    return f"/calibrations/{ident(cal)}/files/{quote(name, safe='')}"


def export_request(cal: str | t.Calibration, fmt: str, **params: Any) -> tuple[str, dict]:
    """(path, params) of `GET /calibrations/{id}/export`."""
    q = _drop_none({"format": fmt, **params})
    return f"/calibrations/{ident(cal)}/export", {
        k: (",".join(map(str, v)) if isinstance(v, list | tuple) else v) for k, v in q.items()}


def report_path(cal: str | Mapping[str, Any]) -> str:
    """Path of a calibration's report page. A rig calibrated from target sessions has its
    own collection: its record (`get_target_rig_calibration`: `cameras`, no `session_id`)
    or the job that made it (its `resource`) says so; an id alone or a calibration record
    (one camera, or a screen session's rig) names one under /calibrations."""
    if isinstance(cal, Mapping) and "resource" in cal:  # a job: its resource names the route
        collection, _, cal_id = str(cal["resource"] or "").rpartition("/")
        if collection not in REPORT_COLLECTIONS or not cal_id:
            raise ValueError(f"report: job {cal.get('id')} made {cal['resource']!r}, not one "
                             "calibration")
        return f"{collection}/{quote(cal_id, safe='')}/report.html"
    target = isinstance(cal, Mapping) and "cameras" in cal and "session_id" not in cal
    return f"{REPORT_COLLECTIONS[1] if target else REPORT_COLLECTIONS[0]}/{ident(cal)}/report.html"


def maps_path(session: str | t.Session, pose: str | t.Pose) -> str:
    """Path of a pose's decoded maps NPZ."""
    return f"/sessions/{ident(session)}/poses/{ident(pose)}/maps.npz"


def frames_zip_path(session: str | t.Session, pose: str | t.Pose) -> str:
    """Path of a pose's captured frames as a zip of frame_NNNN images."""
    return f"/sessions/{ident(session)}/poses/{ident(pose)}/frames.zip"


def job_events_path(job: str | t.Job) -> str:
    """Path of a job's server-sent event stream."""
    return f"/jobs/{ident(job)}/events"


def job_id(job: str | t.Job | dict[str, Any]) -> str:
    """The id of a job given as id or dict."""
    return str(job["id"] if isinstance(job, dict) else job)


# -- multipart uploads from files (streamed: httpx reads open files in chunks) ---------------
def upload_files(field_name: str, paths: Sequence[str | Path]) -> Opener:
    """A function opening the files afresh (for each retry): (httpx files, handles to close)."""
    ps = [Path(p) for p in paths]
    for p in ps:
        if not p.is_file():
            raise FileNotFoundError(f"upload: file not found: {p}")

    def opener() -> tuple[list[tuple[str, Any]], list[Any]]:
        handles = [p.open("rb") for p in ps]
        files = [(field_name, (p.name, fh, "application/octet-stream"))
                 for p, fh in zip(ps, handles, strict=True)]
        return files, handles

    return opener


def import_frames(session: str | t.Session, paths: list[Path],
                  noise_dn: float | None = None) -> Op[t.Job]:
    """Upload a `.npy` stack or frame images (streamed from disk) as a pose; the decode job."""
    data = {"noise_dn": str(noise_dn)} if noise_dn is not None else None
    return Op("POST", f"/sessions/{ident(session)}/poses/import", data=data,
              upload=upload_files("files", paths))


def import_maps(session: str | t.Session, path: Path) -> Op[t.Pose]:
    """Upload a decoded maps NPZ (streamed) as a ready pose."""
    return Op("POST", f"/sessions/{ident(session)}/poses/import-maps",
              upload=upload_files("file", [path]))


# -- streamed downloads -------------------------------------------------------------------------
def download(path: str, dest: str | Path, params: dict[str, Any] | None = None
             ) -> Op[httpx.Headers]:
    """Stream a GET to `dest` (written under a temporary name, then renamed); its headers."""
    return Op("GET", path, params=params, save_to=Path(dest), answer=response_headers)


def download_file(cal: str | t.Calibration, name: str, dest: str | Path) -> Op[Path]:
    """A stored calibration file (model.json, result.json, residuals.png, ...) to `dest`."""
    return Op("GET", file_path(cal, name), save_to=Path(dest), answer=lambda _: Path(dest))


def download_maps(session: str | t.Session, pose: str | t.Pose, dest: str | Path) -> Op[Path]:
    """A pose's decoded maps NPZ to `dest`."""
    return Op("GET", maps_path(session, pose), save_to=Path(dest), answer=lambda _: Path(dest))


def download_frames(session: str | t.Session, pose: str | t.Pose, dest: str | Path,
                    image_format: str = "png") -> Op[Path]:
    """A pose's captured frames as a zip of frame_NNNN.png (or .tif) images to `dest`."""
    return Op("GET", frames_zip_path(session, pose), params={"format": image_format},
              save_to=Path(dest), answer=lambda _: Path(dest))


def download_report(cal: str | Mapping[str, Any], dest: str | Path) -> Op[Path]:
    """A calibration's report as one self-contained HTML file (images inlined) to `dest`:
    one camera's, a screen session's rig's or a target rig's (`report_path`: pass the
    target rig's record or job). While the fit runs or the report is being drawn the
    service answers 202: then `ServiceError` (status 202, type .../not-ready) and `dest`
    is left as it was."""
    return Op("GET", report_path(cal), params={"download": 1},
              answer=saved_page(Path(dest)))


def saved_page(dest: Path) -> Callable[[httpx.Response], Path]:
    """The answer of `download_report`: the page written to `dest` (under a temporary name,
    then renamed), or `ServiceError` for a 202 (not drawn yet) without touching `dest`."""
    def answer(r: httpx.Response) -> Path:
        if r.status_code != 200:
            wait = r.headers.get("retry-after", "a few")
            detail = (f"{r.request.url.path}: the report is not drawn yet (the fit is running "
                      f"or the page is being drawn); ask again in {wait} s")
            raise ServiceError(r.status_code, detail, {
                "type": PROBLEM_BASE + "not-ready", "title": "Report not ready",
                "status": r.status_code, "detail": detail})
        fd, tmp = tempfile.mkstemp(prefix=dest.name + ".", suffix=".part", dir=dest.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(r.content)
            os.replace(tmp, dest)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return dest

    return answer


def export(cal: str | t.Calibration, fmt: str, dest: str | Path,
           **params: Any) -> Op[dict[str, Any]]:
    """`GET /calibrations/{id}/export` to `dest`; returns the export info (exact, residual)."""
    path, query = export_request(cal, fmt, **params)
    return Op("GET", path, params=query, save_to=Path(dest), answer=export_info)


def export_info(r: httpx.Response) -> dict[str, Any]:
    """What an export says of itself (`Phasecal-Export-Info`: exact, residual)."""
    return json.loads(r.headers.get("phasecal-export-info", "{}"))
