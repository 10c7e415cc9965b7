"""A pose's stored frames: decode them again with other options, export them as PNG/TIFF.

A pose captured on several cameras has frames per camera: both routes take `?camera=NAME`
there (one of the pose's `cameras`), and refuse a missing or unknown one by naming them."""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
from fastapi import APIRouter, BackgroundTasks, Depends, Query
from fastapi.responses import FileResponse, JSONResponse
from pydantic import BaseModel, ConfigDict, Field

from api.db import PoseRecord
from api.jobs.poses import RedecodeJob
from api.pose_path import camera_dir, frames_path, stored_indices
from api.problems import Problem
from api.routes.common import (
    PROBLEM_RESPONSES,
    CameraQuery,
    accepted,
    get_pose,
    get_session,
)
from api.services import Services, get_services
from calibration import read_frames
from calibration.shared.plan import plan_from_dict

router = APIRouter(tags=["sessions"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
OPTION_NAMES = ("max_sigma_px", "min_contrast_snr", "min_modulation_snr", "max_ambiguity",
                "consistency_p", "screen_margin_sigma", "edge_margin_blur",
                "saturation_margin", "saturation_dn")


class DecodeRequest(BaseModel):
    """Decode a pose's stored frames again (the new maps replace the old ones on success)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"noise_dn": 1.5, "options": {"max_sigma_px": 0.5}}]})
    noise_dn: float | None = Field(None, gt=0, le=1e4, description="per-frame noise sigma "
                                   "in DN; default: estimated from the residuals")
    options: dict[str, float] = Field(default_factory=dict, max_length=len(OPTION_NAMES),
                                      description="DecodeOptions "
                                      f"fields and saturation_dn: {', '.join(OPTION_NAMES)}")


def _frames_of(svc: Services, session_id: str, pose_id: str,
               camera: str | None) -> tuple[PoseRecord, Path, int]:
    """The pose, its (camera's) frames path and plan frame count; 422 for a camera missing
    on a several-camera pose or not one of its cameras, 409 unless every frame is stored."""
    with svc.db.session() as s:
        pose = get_pose(s, session_id, pose_id)
        total = len(plan_from_dict(get_session(s, session_id).plan, "plan").frames)
    try:
        folder = camera_dir(svc.store.dir_for(pose_id, create=False), camera)
    except ValueError as exc:
        raise Problem(422, "validation-error", str(exc), field="camera") from None
    path = frames_path(folder)
    if pose.source == "capture":
        have = len(stored_indices(folder))
        if have < total:
            raise Problem(409, "frames-incomplete", f"pose {pose_id}: {have} of {total} frames "
                          "stored; resume the capture first")
    elif not path.exists():
        raise Problem(409, "no-frames", f"pose {pose_id} was imported as maps: it has no frames")
    return pose, path, total


@router.post("/sessions/{session_id}/poses/{pose_id}/decode", status_code=202,
             response_model=None)
def redecode_pose(session_id: str, pose_id: str, svc: Svc, body: DecodeRequest | None = None,
                  camera: CameraQuery = None) -> JSONResponse:
    """Decode a pose's stored frames again with other options (a job); one camera's
    (`camera`) on a several-camera pose."""
    req = body or DecodeRequest()
    unknown = sorted(set(req.options) - set(OPTION_NAMES))
    if unknown:
        raise Problem(422, "validation-error", f"options: unknown {unknown}; expected any of "
                      f"{list(OPTION_NAMES)}")
    _, path, _ = _frames_of(svc, session_id, pose_id, camera)
    with svc.db.claim_session() as s:
        pose = get_pose(s, session_id, pose_id)
        if pose.status not in ("ready", "flagged", "failed"):
            raise Problem(409, "conflict", f"pose {pose_id} is {pose.status}; only ready, "
                          "flagged or failed poses are decoded again")
        job = RedecodeJob(svc=svc, session_id=session_id, pose_id=pose_id, frames=path,
                          before=pose.status, noise_dn=req.noise_dn, options=dict(req.options),
                          camera=camera)
        state = svc.jobs.create(s, job)
    return accepted(svc.jobs.start(state.id, job))


@router.get("/sessions/{session_id}/poses/{pose_id}/frames.zip", response_class=FileResponse,
            responses={200: {"content": {"application/zip": {}}}})
def export_frames(session_id: str, pose_id: str, svc: Svc, background: BackgroundTasks,
                  format: Annotated[Literal["png", "tiff"], Query()] = "png",
                  camera: CameraQuery = None) -> FileResponse:
    """The pose's frames as frame_NNNN.png (or .tif) images in a zip (docs/formats.md folder);
    one camera's (`camera`) on a several-camera pose."""
    _, path, _ = _frames_of(svc, session_id, pose_id, camera)
    source = read_frames(path)
    if source.dtype == np.float32 and format == "png":
        raise Problem(422, "unsupported-format", "float32 frames cannot be PNG: use format=tiff")
    scratch = svc.store.temp_dir()
    out = scratch / f"{pose_id}{f'-{camera}' if camera else ''}-frames.zip"
    ext = ".png" if format == "png" else ".tif"
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as zf:
        for i, frame in enumerate(source):
            ok, buf = cv2.imencode(ext, np.asarray(frame))
            if not ok:
                raise Problem(500, "export-failed", f"frame {i}: {ext} encoding failed")
            zf.writestr(f"frame_{i:04d}{ext}", buf.tobytes())
    background.add_task(lambda: (out.unlink(missing_ok=True), scratch.rmdir()))
    return FileResponse(out, media_type="application/zip", filename=out.name)
