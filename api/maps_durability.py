"""A captured pose's maps are made durable after the pose is ready, not before.

The live decode worker writes `maps.npz` into the page cache (no fsync); the server marks
the pose folder `maps.pending` (fsynced, with its folder entry) before it renames the maps
in, reports the pose ready, and a background thread then fsyncs the maps and the folder and
removes the marker. The pose's frames are durable before it is ready (the frame store is
fsynced when the capture ends), so:

- a killed server loses nothing: the page cache holds the whole file;
- after a power cut or kernel crash, a folder still marked `maps.pending` has maps that
  may be incomplete: recovery checks every member's CRC-32 (`intact_maps`); intact maps
  are made durable, others are removed and the pose becomes `interrupted`, so resuming it
  decodes its stored frames again. Maps that may be half-written are never trusted.

A pose of several cameras has a maps file per camera (`cameras/<name>/maps.npz`), each
marked and made durable in its camera's folder the same way; one camera's lost maps make
the whole pose `interrupted` (its resume decodes every camera's stored frames again).
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import zipfile
from pathlib import Path

from sqlalchemy import select

from api.db import Database, PoseRecord
from api.pose_path import CAMERA_SUMMARY, CAMERAS
from calibration.shared.atomic import fsync_path

PENDING = "maps.pending"
MAPS = "maps.npz"
_REQUIRED = ("x", "y", "sigma_x", "sigma_y", "mask", "modulation_x", "modulation_y", "meta")
log = logging.getLogger(__name__)


def mark_pending(pose_dir: Path) -> None:
    """Mark the pose's maps as not yet durable; the mark itself is durable on return, so it
    reaches the disk before the rename of the maps that follows it can."""
    marker = pose_dir / PENDING
    with open(marker, "wb") as fh:
        os.fsync(fh.fileno())
    fsync_path(pose_dir)


def make_durable(pose_dir: Path) -> bool:
    """fsync the pose's maps and folder, then drop the marker; False if the maps are gone
    (the pose was deleted or decoded again meanwhile)."""
    try:
        fsync_path(pose_dir / MAPS)
        fsync_path(pose_dir)
        (pose_dir / PENDING).unlink(missing_ok=True)
        fsync_path(pose_dir)
    except FileNotFoundError:
        return False
    return True


def intact_maps(path: Path) -> str | None:
    """None if `path` is a whole maps NPZ as written (every member's CRC-32 matches, the
    maps members of docs/formats.md are there); otherwise why not, in a few words."""
    try:
        with zipfile.ZipFile(path) as zf:
            names = {n.removesuffix(".npy") for n in zf.namelist()}
            missing = [k for k in _REQUIRED if k not in names]
            if missing:
                return f"members {missing} missing"
            bad = zf.testzip()
            return None if bad is None else f"member {bad} does not match its CRC-32"
    except FileNotFoundError:
        return "no maps file"
    except (OSError, zipfile.BadZipFile, EOFError, ValueError) as exc:
        return f"not a readable zip archive ({exc})"


class MapsSyncer:
    """Background thread making committed maps durable, in order (`submit`); `drain`
    waits for the queue (graceful shutdown, tests)."""

    def __init__(self) -> None:
        self._queue: queue.Queue[Path] = queue.Queue()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def submit(self, pose_dir: Path) -> None:
        with self._lock:
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, daemon=True,
                                                name="maps-durability")
                self._thread.start()
        self._queue.put(pose_dir)

    def _run(self) -> None:
        while True:
            pose_dir = self._queue.get()
            try:
                make_durable(pose_dir)
            except OSError as exc:  # the marker stays: the next start checks the maps
                log.error("maps of %s not made durable: %s", pose_dir.name, exc)
            finally:
                self._queue.task_done()

    def drain(self) -> None:
        """Return once every submitted pose's maps are durable (or failed to be)."""
        self._queue.join()


def recover_pending(db: Database, poses_dir: Path) -> list[str]:
    """At start: poses whose maps were committed but maybe not durable when the last process
    stopped (a one-camera pose's folder, or a camera's folder of a several-camera pose).
    Intact maps are made durable; others are removed and their pose becomes `interrupted`
    (resume decodes its stored frames again). Returns those pose ids."""
    lost: list[str] = []
    markers = sorted([*poses_dir.glob(f"*/{PENDING}"),
                      *poses_dir.glob(f"*/{CAMERAS}/*/{PENDING}")])
    for marker in markers:
        maps_dir = marker.parent
        problem = intact_maps(maps_dir / MAPS)
        if problem is None:
            make_durable(maps_dir)
            continue
        camera = maps_dir.name if maps_dir.parent.name == CAMERAS else None
        pose_id = maps_dir.parent.parent.name if camera else maps_dir.name
        whose = f"camera {camera!r}'s maps were" if camera else "the maps were"
        reason = (f"interrupted: {whose} not yet durable when the server stopped "
                  f"({problem}); resume the pose to decode its stored frames again")
        with db.session() as s:
            pose = s.scalars(select(PoseRecord).where(PoseRecord.id == pose_id)).first()
            if pose is not None and pose.status in ("ready", "flagged"):
                before = f" (it was {pose.status}: {pose.error})" if pose.error else ""
                pose.status, pose.error = "interrupted", reason + before
                pose.valid_pixels = None
                lost.append(pose.id)
        (maps_dir / MAPS).unlink(missing_ok=True)
        if camera:  # the camera shows ready only with its maps and their summary
            (maps_dir / CAMERA_SUMMARY).unlink(missing_ok=True)
        fsync_path(maps_dir)
        marker.unlink()
        fsync_path(maps_dir)
    return lost
