"""Devices and rigs: listing, rig configs, camera settings, moving the simulated screen."""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query
from fastapi.responses import JSONResponse
from sqlalchemy import select

from acquisition.discovery import list_devices as discover
from api.db import RigRecord
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES
from api.schemas import CameraSettingsModel, Device, Rig, RigCreate, ScreenPoseIn
from api.services import Services, get_services

router = APIRouter(tags=["rigs"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]


def _rig_dict(r: RigRecord) -> dict[str, Any]:
    return {"id": r.id, "name": r.name, "config": r.config,
            "simulated": r.config.get("kind", "simulated") == "simulated",
            "created_at": r.created_at}


@router.get("/devices", response_model=list[Device])
def list_devices(svc: Svc) -> list[dict[str, Any]]:
    """Displays and cameras available here (simulated, and real backends when present).

    Aravis network discovery broadcasts, so it is never run from here: the operator's
    `--aravis-address` cameras are probed instead. Rigs created over REST may name only
    devices listed here (and recordings inside the data directory).
    """
    found = discover(aravis_addresses=list(svc.config.aravis_addresses))
    return [dataclasses.asdict(d) for d in found]


@router.get("/rigs", response_model=list[Rig])
def list_rigs(svc: Svc) -> list[dict[str, Any]]:
    """All rigs; `default` is the one the server was started with."""
    with svc.db.session() as s:
        return [_rig_dict(r) for r in s.scalars(select(RigRecord).order_by(RigRecord.created_at))]


@router.post("/rigs", status_code=201, response_model=Rig)
def create_rig(body: RigCreate, svc: Svc) -> JSONResponse:
    """Add a rig from a JSON config (same fields as a rig TOML file)."""
    rec = svc.rigs.create(body.name, body.config)
    return JSONResponse(_rig_dict(rec), status_code=201, headers={"Location": f"/rigs/{rec.id}"})


@router.get("/rigs/{rig_id}", response_model=Rig)
def read_rig(rig_id: str, svc: Svc) -> dict[str, Any]:
    """One rig."""
    rig_id = svc.rigs.resolve(rig_id)
    return _rig_dict(svc.rigs.record(rig_id))


def _settings_dict(s: Any) -> dict[str, Any]:
    return {"exposure_s": s.exposure_s, "gain_db": s.gain_db, "pixel_format": s.pixel_format}


CameraQuery = Annotated[str | None, Query(
    pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$",
    description="a camera of a rig of several cameras (default: the reference camera)")]


def _camera_of(rig: Any, camera: str | None) -> str:
    """The camera a settings request names (default: the reference); 422 naming it if the
    rig has no such camera."""
    if camera is None:
        return rig.reference
    if camera not in rig.cameras:
        raise Problem(422, "validation-error", f"camera: {camera!r} is not a camera of this "
                      f"rig; it has {list(rig.cameras)}", field="camera")
    return camera


@router.get("/rigs/{rig_id}/camera/settings", response_model=CameraSettingsModel)
def read_camera_settings(rig_id: str, svc: Svc, camera: CameraQuery = None) -> dict[str, Any]:
    """The camera settings currently applied (of `camera` on a rig of several)."""
    rig_id = svc.rigs.resolve(rig_id)
    rig = svc.rigs.handle(rig_id).rig
    return _settings_dict(rig.settings_for(_camera_of(rig, camera)))


@router.put("/rigs/{rig_id}/camera/settings", response_model=CameraSettingsModel)
def change_camera_settings(rig_id: str, body: CameraSettingsModel, svc: Svc,
                           camera: CameraQuery = None) -> dict[str, Any]:
    """Change exposure, gain or pixel format (not while a capture runs on the rig: 409). On
    a rig of several cameras, of `camera` alone; without it, the reference camera's, which
    are also the settings of every camera that has none of its own."""
    rig_id = svc.rigs.resolve(rig_id)
    h = svc.rigs.handle(rig_id)
    name = _camera_of(h.rig, camera)
    if not h.lock.acquire(blocking=False):
        raise Problem(409, "rig-busy", f"rig {rig_id} is capturing; change settings between poses")
    try:
        changes = body.model_dump(exclude_none=True)
        wanted = dataclasses.replace(h.rig.settings_for(name), **changes)
        applied = h.rig.cameras[name].configure(wanted)
        if name == h.rig.reference:
            h.rig.settings = applied
        else:
            h.rig.camera_settings[name] = applied
        return _settings_dict(applied)
    finally:
        h.lock.release()


@router.put("/rigs/{rig_id}/screen-pose", response_model=ScreenPoseIn)
def move_screen(rig_id: str, body: ScreenPoseIn, svc: Svc) -> dict[str, Any]:
    """Place the simulated screen for the next capture (409 on a real rig or while capturing)."""
    rig_id = svc.rigs.resolve(rig_id)
    h = svc.rigs.handle(rig_id)
    if not h.lock.acquire(blocking=False):
        raise Problem(409, "rig-busy", f"rig {rig_id} is capturing; move the screen between poses")
    try:
        h.move_screen(body.model_dump())
    finally:
        h.lock.release()
    return body.model_dump()
