"""Live camera preview: JPEG snapshots of a rig's camera, rate-limited and capture-safe.

During a capture the preview shows the frame stored last (a view into the pose's frame
store: the capture loop only records which frame that is, nothing is copied or encoded
there). While the rig is idle a snapshot takes the rig's lock without waiting, grabs one
frame and releases it. Either way one JPEG per rig is encoded at most every
`min_interval_s` and shared by every client asking within that interval.

Frames are scaled by the camera's full scale (from its pixel format), never stretched to
their own maximum: a dark idle frame stays dark instead of turning into amplified sensor
noise, and each preview says where it came from (`idle` or `capture`) and how bright it is,
so a page can say "camera idle, nothing lit" rather than show noise.

The service's routes wait for a preview with `jpeg_async`: a fresh shared JPEG comes back at
once; otherwise the grab and encode (which may block on the camera for up to
`grab_timeout_s`) run on this object's own pool of `PREVIEW_THREADS` threads, so previews
never occupy the server's shared thread pool, however many clients ask.
"""

from __future__ import annotations

import asyncio
import re
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from acquisition.rig import Rig
from api.problems import Problem

MAX_WIDTH = 640  # previews are downscaled to at most this width
JPEG_QUALITY = 80
PREVIEW_THREADS = 4  # at most this many threads ever grab or encode previews
BRIGHT_PERCENTILE = 99.0  # a preview's level: this percentile of its pixels / full scale
T = TypeVar("T")


@dataclass(frozen=True)
class PreviewImage:
    """One encoded preview: the JPEG, where its frame came from, and how bright it is."""

    jpeg: bytes
    source: str  # "idle": a grab between captures; "capture": the newest stored frame
    level: float  # BRIGHT_PERCENTILE of the pixels as a fraction of full scale, 0..1


def full_scale(image: np.ndarray, pixel_format: str | None) -> float:
    """The value of a saturated pixel: 2**bits - 1 from the pixel format's bit depth (Mono12
    -> 4095), else the integer type's maximum; 1.0 for float frames."""
    if image.dtype.kind == "f":
        return 1.0
    bits = re.search(r"(\d+)", pixel_format or "")
    if bits is not None and 1 <= int(bits.group(1)) <= 8 * image.dtype.itemsize:
        return float(2 ** int(bits.group(1)) - 1)
    return float(np.iinfo(image.dtype).max)


def to_jpeg(image: np.ndarray, top: float) -> bytes:
    """An 8-bit, downscaled JPEG of a grey frame whose full scale is `top`."""
    import cv2

    img = np.asarray(image)
    h, w = img.shape[:2]
    if w > MAX_WIDTH:
        img = cv2.resize(img, (MAX_WIDTH, max(1, round(h * MAX_WIDTH / w))),
                         interpolation=cv2.INTER_AREA)
    if img.dtype != np.uint8 or top != 255.0:
        img = np.clip(img.astype(np.float32) * (255.0 / top), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise Problem(500, "preview-failed", "JPEG encoding of the preview failed")
    return buf.tobytes()


def preview_image(image: np.ndarray, pixel_format: str | None, source: str) -> PreviewImage:
    """The JPEG of a frame scaled by its full scale, with its source and brightness."""
    frame = np.asarray(image)
    top = full_scale(frame, pixel_format)
    level = float(np.percentile(frame, BRIGHT_PERCENTILE)) / top if frame.size else 0.0
    return PreviewImage(to_jpeg(frame, top), source, min(max(level, 0.0), 1.0))


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
    """Per-rig preview state: the capture's latest stored frame and the last preview."""

    def __init__(self, min_interval_s: float = 0.1, grab_timeout_s: float = 2.0) -> None:
        self.min_interval_s = min_interval_s
        self.grab_timeout_s = grab_timeout_s
        self._live: dict[str, tuple[Any, int]] = {}  # rig id -> (frame store, index)
        self._jpeg: dict[str, tuple[float, PreviewImage]] = {}  # rig id -> (monotonic time, it)
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

    def jpeg(self, handle: Any) -> PreviewImage:
        """A preview no older than `min_interval_s` (shared), from the capture or an idle grab."""
        rig_id = handle.rig_id
        with self._lock(rig_id):  # one encoder per rig; the others reuse its result
            cached = self._jpeg.get(rig_id)
            if cached is not None and time.monotonic() - cached[0] < self.min_interval_s:
                return cached[1]
            data = self._fresh(handle)
            self._jpeg[rig_id] = (time.monotonic(), data)
            return data

    def shared(self, rig_id: str) -> PreviewImage | None:
        """The rig's preview if it is younger than `min_interval_s` (no lock, no thread)."""
        cached = self._jpeg.get(rig_id)
        if cached is not None and time.monotonic() - cached[0] < self.min_interval_s:
            return cached[1]
        return None

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """`fn(*args)` on the preview pool (for the blocking steps around a preview)."""
        return await asyncio.wrap_future(self._pool.submit(fn, *args))

    async def jpeg_async(self, handle: Any) -> PreviewImage:
        """`jpeg` without blocking the event loop: the shared JPEG, or one made on the pool.
        Cancelling it (a client that left) drops a request still waiting for a thread."""
        data = self.shared(handle.rig_id)
        if data is not None:
            return data
        return await self.run(self.jpeg, handle)

    def _fresh(self, handle: Any) -> PreviewImage:
        pixel_format = handle.rig.settings.pixel_format
        live = self._live.get(handle.rig_id)
        if live is not None:
            store, index = live
            return preview_image(store.frame(index), pixel_format, "capture")
        if not handle.lock.acquire(blocking=False):
            cached = self._jpeg.get(handle.rig_id)
            if cached is not None:
                return cached[1]
            raise Problem(503, "preview-unavailable", f"rig {handle.rig_id}: the camera is "
                          "busy and no frame has been stored yet; retry in a moment")
        try:
            return preview_image(_grab_idle(handle.rig, self.grab_timeout_s), pixel_format, "idle")
        finally:
            handle.lock.release()
