"""Quick intrinsics of a session: the papers' closed-form methods on its poses' white flats
(before any decoding) or decoded maps, as a job; the latest result is kept per session."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse
from sqlalchemy import select

from api.db import PoseRecord
from api.jobs.intrinsics import RESULT, IntrinsicsJob
from api.problems import Problem
from api.routes.common import PROBLEM_RESPONSES, accepted, get_session
from api.schemas import IntrinsicsCreate
from api.services import Services, get_services
from api.store import check_id
from calibration import white_flat_index
from calibration.shared.frame_store import FrameStore
from calibration.shared.plan import plan_from_dict

router = APIRouter(tags=["intrinsics"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]


def _flat_source(svc: Services, pose: PoseRecord, index: int) -> str:
    """The pose's captured frames (folder or stack) if its white flat frame is stored."""
    folder = svc.store.dir_for(pose.id)
    store = FrameStore(folder)
    if store.frames_path.is_file():
        # an uploaded stack is whole; a captured one holds what its done-markers say
        if not store.done_path.is_file() or index in store.stored():
            return str(store.frames_path)
        raise Problem(409, "no-white-flat", f"pose {pose.id}: its capture has not stored the "
                      f"white flat frame (plan frame {index}) yet; resume the capture first")
    frames = folder / "frames"
    if any((frames / f"frame_{index:04d}.{ext}").is_file() for ext in ("png", "tif", "tiff")):
        return str(frames)
    raise Problem(409, "no-white-flat", f"pose {pose.id} has no stored white flat frame "
                  f"(plan frame {index}); imported maps carry none: use source=maps")


def _poses(s: Any, session_id: str, ids: list[str] | None, source: str) -> list[PoseRecord]:
    """The chosen poses of the session (default: all that have what `source` needs)."""
    if ids is None:
        recs = list(s.scalars(select(PoseRecord).where(PoseRecord.session_id == session_id)
                              .order_by(PoseRecord.index)))
        if source == "maps":
            recs = [p for p in recs if p.status in ("ready", "flagged")]
        return recs
    out = []
    for pid in dict.fromkeys(ids):
        check_id(pid, "pose", "pose")
        p = s.get(PoseRecord, pid)
        if p is None or p.session_id != session_id:
            raise Problem(422, "validation-error",
                          f"pose_ids: pose {pid!r} is not a pose of session {session_id}")
        if source == "maps" and p.status not in ("ready", "flagged"):
            raise Problem(409, "not-ready", f"pose_ids: pose {pid} is {p.status}; its maps "
                          "exist once it is ready (or use source=flats)")
        out.append(p)
    return out


@router.post("/sessions/{session_id}/intrinsics", status_code=202, response_model=None,
             responses={202: {"description": "intrinsics job accepted; Location: /jobs/<id>"}})
def start_intrinsics(session_id: str, body: IntrinsicsCreate, svc: Svc) -> JSONResponse:
    """Estimate K from the session's white flats or maps (rectangle, selfcal or rotation)."""
    with svc.db.session() as s:
        plan = plan_from_dict(get_session(s, session_id).plan, f"session {session_id} plan")
        poses = _poses(s, session_id, body.pose_ids, body.source)
        need = {"rectangle": 3 if body.square_pixels else 4, "selfcal": 3, "rotation": 3}
        if len(poses) < need[body.method]:
            raise Problem(409, "too-few-poses", f"{body.method} needs >= {need[body.method]} "
                          f"poses with {body.source}; session {session_id} has {len(poses)}")
        if body.source == "flats":
            index = white_flat_index(plan)
            paths = [_flat_source(svc, p, index) for p in poses]
        else:
            paths = [str(svc.store.file(p.id, "maps.npz")) for p in poses]
        # one quick-intrinsics job per session at a time (409 job-active otherwise)
        job = IntrinsicsJob(svc=svc, session_id=session_id, pose_ids=[p.id for p in poses],
                            paths=paths, source=body.source, method=body.method,
                            square_pixels=body.square_pixels, zero_skew=body.zero_skew)
        state = svc.jobs.create(s, job)
    return accepted(svc.jobs.start(state.id, job))


@router.get("/sessions/{session_id}/intrinsics")
def read_intrinsics(session_id: str, svc: Svc) -> dict[str, Any]:
    """The session's latest quick-intrinsics result (phasecal.intrinsics/1)."""
    with svc.db.session() as s:
        get_session(s, session_id)
    path = svc.store.dir_for(session_id) / RESULT
    if not path.is_file():
        raise Problem(404, "not-found", f"session {session_id} has no intrinsics yet; POST "
                      f"/sessions/{session_id}/intrinsics to estimate them")
    return json.loads(path.read_text())
