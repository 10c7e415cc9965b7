"""Live camera preview: `GET /rigs/{id}/camera/preview` (MJPEG) and `.../preview.jpg`.

Both run on the event loop; grabs and encodes go to the preview's own small thread pool
(`api.live_preview`). A stream holds a slot of the app's preview `StreamLimiter` and ends
when the client hangs up or stops reading (`api.stream_limits`).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response, StreamingResponse

from api.live_preview import LivePreview, PreviewImage
from api.problems import Problem
from api.rigs import RigHandle
from api.routes.common import PROBLEM_RESPONSES, TOO_MANY_STREAMS
from api.services import Services
from api.stream_limits import PREVIEW, GuardedStream, client_address, stream_limiter

router = APIRouter(tags=["rigs"], responses=PROBLEM_RESPONSES)
log = logging.getLogger("phasecal.api")
BOUNDARY = "phasecal-frame"
MEDIA_TYPE = f"multipart/x-mixed-replace; boundary={BOUNDARY}"
MIN_FPS = 0.2  # slower previews are snapshots: poll preview.jpg
MAX_FPS = 10.0  # the shared JPEG is renewed at most every 0.1 s
SOURCE_HEADER = "Phasecal-Preview-Source"  # idle | capture
LEVEL_HEADER = "Phasecal-Preview-Level"  # 99th-percentile pixel / full scale, 0..1


def _handle(svc: Services, rig_id: str) -> RigHandle:
    """The opened rig a path names (`default` too); 404 for an unknown rig. Blocking."""
    rig_id = svc.rigs.resolve(rig_id)
    svc.rigs.record(rig_id)  # 404 for an unknown rig
    return svc.rigs.handle(rig_id)


def _part(data: bytes) -> bytes:
    return (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
            f"Content-Length: {len(data)}\r\n\r\n").encode() + data + b"\r\n"


async def _parts(preview: LivePreview, handle: RigHandle, first: PreviewImage, fps: float,
                 frames: int | None) -> AsyncIterator[bytes]:
    """MJPEG parts at `fps`, paced from each frame's start; waits hold no thread."""
    data, sent, period = first, 0, 1.0 / fps
    due = time.monotonic()
    while True:
        yield _part(data.jpeg)
        sent += 1
        if frames is not None and sent >= frames:
            return
        due = max(due + period, time.monotonic())  # behind (slow client): no burst after
        await asyncio.sleep(due - time.monotonic())
        try:
            data = await preview.jpeg_async(handle)
        except Problem as exc:  # e.g. the camera went away: end the stream, the client retries
            log.info("preview of rig %s ended: %s", handle.rig_id, exc.detail)
            return


@router.get("/rigs/{rig_id}/camera/preview.jpg", response_class=Response,
            responses={200: {"content": {"image/jpeg": {}}}})
async def preview_jpeg(rig_id: str, request: Request) -> Response:
    """One JPEG of the rig's camera (the newest captured frame during a capture), scaled
    by the camera's full scale. Headers say where the frame came from (`idle` or `capture`)
    and its brightness (99th-percentile pixel over full scale), so a client can tell a dark,
    idle camera from a lit pattern."""
    svc: Services = request.app.state.services
    handle = await svc.preview.run(_handle, svc, rig_id)
    shot = await svc.preview.jpeg_async(handle)
    return Response(shot.jpeg, media_type="image/jpeg", headers={
        "Cache-Control": "no-store", SOURCE_HEADER: shot.source,
        LEVEL_HEADER: f"{shot.level:.4f}"})


@router.get("/rigs/{rig_id}/camera/preview", response_class=StreamingResponse,
            responses={200: {"content": {MEDIA_TYPE: {}}}, **TOO_MANY_STREAMS})
async def preview_stream(
    rig_id: str, request: Request,
    fps: Annotated[float, Query(ge=MIN_FPS, le=MAX_FPS, allow_inf_nan=False)] = 5.0,
    frames: Annotated[int | None, Query(ge=1)] = None,
) -> Response:
    """MJPEG stream of the rig's camera at `fps` (0.2 to 10) frames a second; `frames`
    ends it after that many (default: until the client disconnects). Each client address
    may hold a few streams at once, the server a few dozen (429 with Retry-After beyond)."""
    svc: Services = request.app.state.services
    slot = stream_limiter(request.app, PREVIEW).acquire(client_address(request))
    try:
        handle = await svc.preview.run(_handle, svc, rig_id)
        first = await svc.preview.jpeg_async(handle)  # problems (busy, unknown) before the stream
    except BaseException:
        slot.release()
        raise
    return GuardedStream(_parts(svc.preview, handle, first, fps, frames), slot,
                         media_type=MEDIA_TYPE, headers={"Cache-Control": "no-store"})
