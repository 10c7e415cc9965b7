"""Free space in the data directory: what a capture needs, a reserve for the database, and
"no space left" recognised wherever it surfaces (OSError, SQLite, a worker's exception).

A full disk is a state of the service, not a crash. A capture is refused up front (507)
when its frames and maps would not fit; a job that still runs out of space ends `failed`
with a reason that says so; and a small preallocated reserve file is released the moment
the database reports that it is full, so the job's outcome, its claims and the DELETEs
that free space can still be written. The reserve is made again once there is room.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import shutil
import sqlite3
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from api.problems import MEDIA_TYPE, Problem, StartTracking, problem_body
from calibration.shared.atomic import allocate

log = logging.getLogger("phasecal.storage")

RESERVE_NAME = "space.reserve"
MAPS_BYTES_PER_PIXEL = 41  # x, y float64; sigmas, modulations, blurs float32; mask
NO_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
SQLITE_FULL = 13  # sqlite3's result code for "database or disk is full"
NO_SPACE = "no space left on device"  # how a job's reason starts when space ran out

T = TypeVar("T")


def is_no_space(exc: BaseException | None) -> bool:
    """True when `exc`, or an exception it was raised from, means the disk (or the user's
    quota) is full: ENOSPC/EDQUOT, or SQLite's "database or disk is full" (also wrapped by
    SQLAlchemy, or re-raised by a worker process with only its message)."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in NO_SPACE_ERRNOS:
            return True
        if isinstance(exc, sqlite3.Error) and getattr(exc, "sqlite_errorcode", None) == SQLITE_FULL:
            return True
        text = str(exc)
        if "database or disk is full" in text or "No space left on device" in text \
                or "Disk quota exceeded" in text:
            return True
        exc = getattr(exc, "orig", None) or exc.__cause__ or exc.__context__
    return False


def frame_bytes_per_pixel(bit_depth: int) -> int:
    """Bytes a stored frame takes per pixel: uint8 up to 8 bits, uint16 above (the service's
    controller stores single exposures)."""
    return 1 if bit_depth <= 8 else 2


def pose_bytes(frames: int, width: int, height: int, bit_depth: int) -> int:
    """Disk a captured pose needs: its raw frame store and its decoded maps."""
    pixels = width * height
    return frames * pixels * frame_bytes_per_pixel(bit_depth) + pixels * MAPS_BYTES_PER_PIXEL


def mib(n: float) -> str:
    """A byte count for people (MiB with one decimal)."""
    return f"{n / (1 << 20):.1f} MiB"


@dataclass(frozen=True)
class SpaceReport:
    """The data directory's filesystem: free and total bytes, and the reserve's state."""

    free_bytes: int
    total_bytes: int
    reserve_bytes: int
    reserve_held: bool
    #: below this the service is degraded: the margin, or what the last capture refused or
    #: cut off for lack of space needed (until that much is free again)
    wanted_bytes: int

    @property
    def degraded(self) -> str | None:
        """Why the service cannot be trusted to store the next results, or None."""
        if not self.reserve_held:
            return (f"low on space: the database reserve is in use ({mib(self.free_bytes)} "
                    "free in the data directory); delete poses, sessions or calibrations")
        if self.free_bytes < self.wanted_bytes:
            return (f"low on space: {mib(self.free_bytes)} free in the data directory, "
                    f"{mib(self.wanted_bytes)} wanted; delete poses, sessions or calibrations")
        return None

    def to_dict(self) -> dict[str, object]:
        """Plain data for `GET /health`."""
        return {"free_bytes": self.free_bytes, "total_bytes": self.total_bytes,
                "wanted_bytes": self.wanted_bytes, "reserve_bytes": self.reserve_bytes,
                "reserve_held": self.reserve_held}


class DiskSpace:
    """The data directory's space budget and its database reserve.

    `reserve_bytes` are held in a preallocated file beside the database; `release` frees
    them when a write fails for lack of space, `restore` takes them back once the free
    space allows (after a DELETE, or when `report` sees room again).
    """

    def __init__(self, root: Path, reserve_bytes: int, margin_bytes: int) -> None:
        self.root = Path(root)
        self.reserve_bytes = reserve_bytes
        self.margin_bytes = margin_bytes
        self.reserve_path = self.root / RESERVE_NAME
        self.shortfall = 0  # bytes the last refused or cut-off write wanted free (0: none)
        self._lock = threading.Lock()
        self.restore()

    # -- the reserve -------------------------------------------------------------------
    def reserve_held(self) -> bool:
        """True while the reserve file holds its full size."""
        try:
            return self.reserve_path.stat().st_size >= self.reserve_bytes
        except OSError:
            return False

    def restore(self) -> bool:
        """Allocate the reserve if it is missing and the disk has room for it and the margin
        beyond; True when it is held afterwards."""
        if self.reserve_bytes <= 0:
            return True
        with self._lock:
            if self.reserve_held():
                return True
            if self.free_bytes() < self.reserve_bytes + self.margin_bytes:
                return False
            tmp = self.reserve_path.with_name(RESERVE_NAME + ".tmp")
            try:
                fd = os.open(tmp, os.O_CREAT | os.O_WRONLY | os.O_TRUNC, 0o600)
                try:
                    allocate(fd, self.reserve_bytes)
                finally:
                    os.close(fd)
                os.replace(tmp, self.reserve_path)
            except OSError as exc:
                tmp.unlink(missing_ok=True)
                log.warning("could not allocate the %s space reserve: %s",
                            mib(self.reserve_bytes), exc)
                return False
            return True

    def release(self) -> bool:
        """Free the reserve for the database; True if it was held."""
        with self._lock:
            try:
                self.reserve_path.unlink()
            except FileNotFoundError:
                return False
            log.warning("no space left in %s: released the %s database reserve", self.root,
                        mib(self.reserve_bytes))
            return True

    def retrying(self, write: Callable[[], T]) -> T:
        """Run a database write; if it fails for lack of space, release the reserve and run
        it once more (a second failure is raised)."""
        try:
            return write()
        except Exception as exc:
            if not is_no_space(exc) or not self.release():
                raise
        return write()

    # -- space -------------------------------------------------------------------------
    def free_bytes(self) -> int:
        """Bytes an unprivileged writer can still use on the data directory's filesystem."""
        return int(shutil.disk_usage(self.root).free)

    def report(self) -> SpaceReport:
        """Free and total space and the reserve (taken back first if there is room now)."""
        held = self.restore()
        usage = shutil.disk_usage(self.root)
        if usage.free >= self.shortfall:
            self.shortfall = 0  # space was freed since
        return SpaceReport(int(usage.free), int(usage.total), self.reserve_bytes, held,
                           max(self.margin_bytes, self.shortfall))

    def require(self, needed: int, what: str) -> None:
        """507 when `needed` bytes plus the margin do not fit in the free space (the reserve
        is not counted as free: it belongs to the database, also while it is released and
        its bytes show as free on the disk; otherwise whether a request fits would depend on
        whether some write happened to release it)."""
        released = self.reserve_bytes if self.reserve_bytes > 0 and not self.reserve_held() else 0
        free = max(self.free_bytes() - released, 0)
        want = needed + self.margin_bytes
        if free < want:
            self.shortfall = want
            raise Problem(507, "insufficient-storage",
                          f"{what} needs about {mib(want)} in the data directory ({mib(needed)} "
                          f"+ {mib(self.margin_bytes)} margin) and {mib(free)} is free: delete "
                          "poses, sessions or calibrations, or free space on that disk",
                          needed_bytes=want, free_bytes=free)

    def ran_out(self) -> int:
        """Note that a write found no space: the service reports itself degraded until the
        margin is free beyond what is free now (returned)."""
        left = self.free_bytes()
        self.shortfall = max(self.shortfall, left + self.margin_bytes)
        return left

    def no_space_reason(self, exc: BaseException) -> str:
        """The reason a job that ran out of space ends with: says so, and how much is free."""
        try:
            free = mib(self.ran_out())
        except OSError:
            free = "unknown"
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        return (f"{NO_SPACE} in the data directory ({free} free): "
                f"{type(exc).__name__}: {first}"[:2000])


class NoSpaceMiddleware:
    """Answers a request that failed for lack of space with 507 problem+json (how much is
    free, what to do) instead of a 500, and releases the database reserve so that the
    DELETEs which free space can still be written."""

    def __init__(self, app: Any, space: DiskSpace) -> None:
        self.app = app
        self.space = space

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        tracked = StartTracking(send)
        try:
            await self.app(scope, receive, tracked)
        except Exception as exc:
            if not is_no_space(exc):
                raise
            self.space.release()
            log.warning("no space left on %s %s: %s", scope.get("method"), scope.get("path"), exc)
            if tracked.started:  # the answer went out; what failed after it was bookkeeping
                return
            body = json.dumps(problem_body(
                507, "insufficient-storage",
                f"{NO_SPACE} in the data directory ({mib(self.space.ran_out())} free): delete "
                "poses, sessions or calibrations, or free space on that disk, then retry",
                scope.get("path"))).encode()
            await send({"type": "http.response.start", "status": 507,
                        "headers": [(b"content-type", MEDIA_TYPE.encode()),
                                    (b"content-length", str(len(body)).encode())]})
            await send({"type": "http.response.body", "body": body})
