"""Live camera preview: JPEG snapshots of a rig's camera, rate-limited and capture-safe.

During a capture the preview shows the frame stored last (a view into the pose's frame
store: the capture loop only records which frame that is, nothing is copied or encoded
there). While the rig is idle a snapshot takes the rig's lock without waiting, grabs one
frame and releases it. Either way one JPEG per rig is encoded at most every
`min_interval_s` and shared by every client asking within that interval.

The service's routes wait for a JPEG with `jpeg_async`: a fresh shared JPEG comes back at
once; otherwise the grab and encode (which may block on the camera for up to
`grab_timeout_s`) run on this object's own pool of `PREVIEW_THREADS` threads, so previews
never occupy the server's shared thread pool, however many clients ask.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

import numpy as np

from acquisition.rig import Rig
from api.problems import Problem

MAX_WIDTH = 640  # previews are downscaled to at most this width
JPEG_QUALITY = 80
PREVIEW_THREADS = 4  # at most this many threads ever grab or encode previews
T = TypeVar("T")


def to_jpeg(image: np.ndarray) -> bytes:
    """An 8-bit, downscaled JPEG of a grey frame (uint16/float32 scaled by their maximum)."""
    import cv2

    img = np.asarray(image)
    h, w = img.shape[:2]
    if w > MAX_WIDTH:
        img = cv2.resize(img, (MAX_WIDTH, max(1, round(h * MAX_WIDTH / w))),
                         interpolation=cv2.INTER_AREA)
    if img.dtype != np.uint8:
        top = float(img.max()) or 1.0
        img = np.clip(img.astype(np.float32) * (255.0 / top), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise Problem(500, "preview-failed", "JPEG encoding of the preview failed")
    return buf.tobytes()


def _grab_idle(rig: Rig, timeout_s: float) -> np.ndarray:
    """One frame from an idle rig's camera with its configured settings."""
    cam = rig.camera
    mode = cam.configure(rig.settings).trigger_mode
    if mode == "hardware":
        raise Problem(409, "preview-unavailable", "the camera is in hardware-trigger mode; "
                      "an idle preview needs software or free-running trigger")
    cam.start()
    try:
        if mode == "software":
            cam.trigger()
        return cam.grab(timeout_s).image
    finally:
        cam.stop()


class LivePreview:
    """Per-rig preview state: the capture's latest stored frame and the last JPEG."""

    def __init__(self, min_interval_s: float = 0.1, grab_timeout_s: float = 2.0) -> None:
        self.min_interval_s = min_interval_s
        self.grab_timeout_s = grab_timeout_s
        self._live: dict[str, tuple[Any, int]] = {}  # rig id -> (frame store, index)
        self._jpeg: dict[str, tuple[float, bytes]] = {}  # rig id -> (monotonic time, JPEG)
        self._locks: dict[str, threading.Lock] = {}
        self._guard = threading.Lock()
        self._pool = ThreadPoolExecutor(PREVIEW_THREADS, thread_name_prefix="phasecal-preview")

    def publisher(self, rig_id: str) -> Callable[[Any, int], None]:
        """The capture's per-frame callback: remember which stored frame is newest."""

        def publish(store: Any, index: int) -> None:
            self._live[rig_id] = (store, index)

        return publish

    def capture_ended(self, rig_id: str) -> None:
        """The rig's capture released the camera: idle snapshots again."""
        self._live.pop(rig_id, None)

    def _lock(self, rig_id: str) -> threading.Lock:
        with self._guard:
            return self._locks.setdefault(rig_id, threading.Lock())

    def jpeg(self, handle: Any) -> bytes:
        """A JPEG no older than `min_interval_s` (shared), from the capture or an idle grab."""
        rig_id = handle.rig_id
        with self._lock(rig_id):  # one encoder per rig; the others reuse its result
            cached = self._jpeg.get(rig_id)
            if cached is not None and time.monotonic() - cached[0] < self.min_interval_s:
                return cached[1]
            data = self._fresh(handle)
            self._jpeg[rig_id] = (time.monotonic(), data)
            return data

    def shared(self, rig_id: str) -> bytes | None:
        """The rig's JPEG if it is younger than `min_interval_s` (no lock, no thread)."""
        cached = self._jpeg.get(rig_id)
        if cached is not None and time.monotonic() - cached[0] < self.min_interval_s:
            return cached[1]
        return None

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """`fn(*args)` on the preview pool (for the blocking steps around a preview)."""
        return await asyncio.wrap_future(self._pool.submit(fn, *args))

    async def jpeg_async(self, handle: Any) -> bytes:
        """`jpeg` without blocking the event loop: the shared JPEG, or one made on the pool.
        Cancelling it (a client that left) drops a request still waiting for a thread."""
        data = self.shared(handle.rig_id)
        if data is not None:
            return data
        return await self.run(self.jpeg, handle)

    def _fresh(self, handle: Any) -> bytes:
        live = self._live.get(handle.rig_id)
        if live is not None:
            store, index = live
            return to_jpeg(store.frame(index))
        if not handle.lock.acquire(blocking=False):
            cached = self._jpeg.get(handle.rig_id)
            if cached is not None:
                return cached[1]
            raise Problem(503, "preview-unavailable", f"rig {handle.rig_id}: the camera is "
                          "busy and no frame has been stored yet; retry in a moment")
        try:
            return to_jpeg(_grab_idle(handle.rig, self.grab_timeout_s))
        finally:
            handle.lock.release()
