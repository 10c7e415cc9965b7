"""Durable records in SQLite (SQLAlchemy 2, WAL): rigs, sessions, poses, calibrations, jobs."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import JSON, Float, ForeignKey, Integer, LargeBinary, String, create_engine, event
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, sessionmaker


class Base(DeclarativeBase):
    """Declarative base of all tables."""


class RigRecord(Base):
    """A rig: display + camera + screen geometry + settings (the config as JSON)."""

    __tablename__ = "rigs"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    config: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[float] = mapped_column(Float, default=time.time)


class SessionRecord(Base):
    """A session: one rig and one pattern plan, several poses."""

    __tablename__ = "sessions"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    rig_id: Mapped[str | None] = mapped_column(ForeignKey("rigs.id"), nullable=True)
    name: Mapped[str] = mapped_column(String(200), default="")
    plan: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[float] = mapped_column(Float, default=time.time)


class PoseRecord(Base):
    """One pose of a session: captured or imported frames, then decoded maps."""

    __tablename__ = "poses"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id"), index=True)
    index: Mapped[int] = mapped_column(Integer)
    source: Mapped[str] = mapped_column(String(16))
    status: Mapped[str] = mapped_column(String(16))
    job_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    valid_pixels: Mapped[int | None] = mapped_column(Integer, nullable=True)
    width: Mapped[int | None] = mapped_column(Integer, nullable=True)
    height: Mapped[int | None] = mapped_column(Integer, nullable=True)
    frames_done: Mapped[int] = mapped_column(Integer, default=0)
    screen_pose: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    error: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    created_at: Mapped[float] = mapped_column(Float, default=time.time)


class CalibrationRecord(Base):
    """A calibration of chosen poses with one model."""

    __tablename__ = "calibrations"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id"), index=True)
    model: Mapped[str] = mapped_column(String(32))
    pose_ids: Mapped[list[str]] = mapped_column(JSON)
    heldout_pose_ids: Mapped[list[str]] = mapped_column(JSON, default=list)
    options: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    status: Mapped[str] = mapped_column(String(16))
    job_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    stats: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    exports: Mapped[list[str]] = mapped_column(JSON, default=list)
    error: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    created_at: Mapped[float] = mapped_column(Float, default=time.time)


class TargetSessionRecord(Base):
    """A session of a passive target (a board, or surveyed points): its views are target
    observations, uploaded or detected in uploaded images (api/routes/observations.py)."""

    __tablename__ = "target_sessions"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    name: Mapped[str] = mapped_column(String(200), default="")
    target: Mapped[str] = mapped_column(String(200))  # a board description, or "points"
    created_at: Mapped[float] = mapped_column(Float, default=time.time)


class TargetViewRecord(Base):
    """One view of a target session: a `phasecal.observations/1` file in its folder."""

    __tablename__ = "target_views"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("target_sessions.id"), index=True)
    index: Mapped[int] = mapped_column(Integer)
    name: Mapped[str] = mapped_column(String(200))
    source: Mapped[str] = mapped_column(String(16))  # "observations" or "image"
    points: Mapped[int] = mapped_column(Integer)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[float] = mapped_column(Float, default=time.time)


class TargetCalibrationRecord(Base):
    """A calibration of chosen views of a target session with one model."""

    __tablename__ = "target_calibrations"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("target_sessions.id"), index=True)
    model: Mapped[str] = mapped_column(String(32))
    view_ids: Mapped[list[str]] = mapped_column(JSON)
    options: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    cross_validate: Mapped[int] = mapped_column(Integer, default=0)
    stats: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[float] = mapped_column(Float, default=time.time)


class TargetRigCalibrationRecord(Base):
    """A rig calibration from target sessions, one per camera, their views paired across
    cameras by shot name (api/routes/target_rig.py); its folder holds rig.json."""

    __tablename__ = "target_rig_calibrations"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    # camera -> {"session_id": ..., "views": {shot: view id}}
    cameras: Mapped[dict[str, Any]] = mapped_column(JSON)
    heldout_shots: Mapped[list[str]] = mapped_column(JSON, default=list)
    reference: Mapped[str] = mapped_column(String(64))
    camera_models: Mapped[dict[str, str]] = mapped_column(JSON)
    options: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    status: Mapped[str] = mapped_column(String(16))
    job_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    stats: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    error: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    created_at: Mapped[float] = mapped_column(Float, default=time.time)


class JobRecord(Base):
    """A long operation: capture, decode or calibrate, with progress and outcome."""

    __tablename__ = "jobs"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    kind: Mapped[str] = mapped_column(String(16), index=True)
    status: Mapped[str] = mapped_column(String(16), index=True)
    stage: Mapped[str] = mapped_column(String(64), default="")
    done: Mapped[int] = mapped_column(Integer, default=0)
    total: Mapped[int] = mapped_column(Integer, default=0)
    resource: Mapped[str | None] = mapped_column(String(200), nullable=True)
    session_id: Mapped[str | None] = mapped_column(String(32), nullable=True, index=True)
    error: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    created_at: Mapped[float] = mapped_column(Float, default=time.time, index=True)
    started_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished_at: Mapped[float | None] = mapped_column(Float, nullable=True)


class JobLockRecord(Base):
    """An active job's claim on a pose or calibration: one active job per resource.

    The primary key makes a second claim fail even if two requests race; rows are
    removed in the transaction that ends the job (and all of them at restart).
    """

    __tablename__ = "job_locks"
    key: Mapped[str] = mapped_column(String(32), primary_key=True)
    job_id: Mapped[str] = mapped_column(String(32), index=True)


class IdempotencyRecord(Base):
    """The stored answer to a POST with an Idempotency-Key, replayed on retry."""

    __tablename__ = "idempotency"
    key: Mapped[str] = mapped_column(String(200), primary_key=True)
    method: Mapped[str] = mapped_column(String(8))
    path: Mapped[str] = mapped_column(String(500))
    body_sha256: Mapped[str] = mapped_column(String(64))
    status_code: Mapped[int] = mapped_column(Integer)
    headers: Mapped[dict[str, str]] = mapped_column(JSON)
    body: Mapped[bytes] = mapped_column(LargeBinary)
    created_at: Mapped[float] = mapped_column(Float, default=time.time)


class Database:
    """Engine + session factory for one SQLite file in WAL mode."""

    def __init__(self, path: Path) -> None:
        self.engine = create_engine(
            f"sqlite:///{path}",
            connect_args={"check_same_thread": False, "timeout": 30},
            pool_size=8,
            max_overflow=16,
        )
        event.listen(self.engine, "connect", _sqlite_pragmas)
        Base.metadata.create_all(self.engine)
        self._factory = sessionmaker(self.engine, expire_on_commit=False)
        self._claim_lock = threading.Lock()

    @contextmanager
    def session(self) -> Iterator[Session]:
        """A transaction: committed on success, rolled back on error."""
        with self._factory() as s, s.begin():
            yield s

    @contextmanager
    def claim_session(self) -> Iterator[Session]:
        """A transaction that checks state and then claims it (e.g. starts a job), serialized
        with every other such transaction of this process, so check and insert cannot race
        (SQLite would otherwise refuse the second writer's stale snapshot: 'database is
        locked')."""
        with self._claim_lock, self.session() as s:
            yield s

    def close(self) -> None:
        """Dispose of pooled connections."""
        self.engine.dispose()


def _sqlite_pragmas(dbapi_conn: Any, _record: Any) -> None:
    """WAL for concurrent readers during writes; NORMAL sync is durable enough with WAL."""
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.close()
