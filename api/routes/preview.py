"""Live camera preview: `GET /rigs/{id}/camera/preview` (MJPEG) and `.../preview.jpg`."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Annotated

from fastapi import APIRouter, Depends, Query
from fastapi.responses import Response, StreamingResponse

from api.routes.common import PROBLEM_RESPONSES
from api.services import Services, get_services
from api.store import check_id

router = APIRouter(tags=["rigs"], responses=PROBLEM_RESPONSES)
Svc = Annotated[Services, Depends(get_services)]
BOUNDARY = "phasecal-frame"
MAX_FPS = 10.0


def _handle(svc: Services, rig_id: str):
    check_id(rig_id, "rig", "rig")
    svc.rigs.record(rig_id)  # 404 for an unknown rig
    return svc.rigs.handle(rig_id)


@router.get("/rigs/{rig_id}/camera/preview.jpg", response_class=Response,
            responses={200: {"content": {"image/jpeg": {}}}})
def preview_jpeg(rig_id: str, svc: Svc) -> Response:
    """One JPEG of the rig's camera (the newest captured frame during a capture)."""
    data = svc.preview.jpeg(_handle(svc, rig_id))
    return Response(data, media_type="image/jpeg", headers={"Cache-Control": "no-store"})


@router.get("/rigs/{rig_id}/camera/preview", response_class=StreamingResponse,
            responses={200: {"content": {f"multipart/x-mixed-replace; boundary={BOUNDARY}": {}}}})
def preview_stream(rig_id: str, svc: Svc,
                   fps: Annotated[float, Query(gt=0, le=MAX_FPS)] = 5.0,
                   frames: Annotated[int | None, Query(ge=1)] = None) -> StreamingResponse:
    """MJPEG stream of the rig's camera at up to `fps` (at most 10) frames a second; `frames`
    ends it after that many (default: until the client disconnects)."""
    handle = _handle(svc, rig_id)
    first = svc.preview.jpeg(handle)  # problems (busy, unknown) before the stream starts

    def parts() -> Iterator[bytes]:
        data, sent = first, 0
        while True:
            yield (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                   f"Content-Length: {len(data)}\r\n\r\n").encode() + data + b"\r\n"
            sent += 1
            if frames is not None and sent >= frames:
                return
            time.sleep(1.0 / fps)
            data = svc.preview.jpeg(handle)

    return StreamingResponse(parts(), media_type=f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                             headers={"Cache-Control": "no-store"})
