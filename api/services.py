"""The service's long-lived parts, built once per app and reached from routes via the request."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from fastapi import Request

from api.config import ServiceConfig
from api.db import Database
from api.jobs.manager import JobManager
from api.live_preview import LivePreview
from api.maps_durability import MapsSyncer, recover_pending
from api.pose_path import stored_indices
from api.recovery import mark_interrupted
from api.rigs import RigManager
from api.storage import DiskSpace
from api.store import DataStore
from api.worker.executor import Executor, make_executor

log = logging.getLogger("phasecal.service")


@dataclass
class Services:
    """Config, data directory, database, executor, job manager and rigs of one server."""

    config: ServiceConfig
    store: DataStore
    db: Database
    executor: Executor
    jobs: JobManager
    rigs: RigManager
    preview: LivePreview
    #: free space in the data directory and the database's reserve (api/storage.py)
    space: DiskSpace
    #: makes captured poses' maps durable after they are ready (api/maps_durability.py)
    maps_sync: MapsSyncer = field(default_factory=MapsSyncer)

    @classmethod
    def build(cls, config: ServiceConfig) -> Services:
        """Open (or create) the data directory and database; recover interrupted work."""
        store = DataStore(config.data_dir)
        space = DiskSpace(store.root, config.space_reserve_bytes, config.min_free_bytes)
        db = Database(store.db_path)
        executor = make_executor(config.executor)
        jobs = JobManager(db, executor, space)
        try:
            rigs = RigManager(db, config.rig, store.root, config.rigs_dir,
                              tuple(config.aravis_addresses))
        except BaseException:  # a bad --rig/--rigs-dir: stop the workers before failing
            executor.shutdown(wait=False)
            db.close()
            raise
        services = cls(config, store, db, executor, jobs, rigs, LivePreview(), space)
        space.retrying(services.recover)  # (on a full disk: with the reserve)
        return services

    def recover(self) -> None:
        """Jobs left active by a previous process become interrupted, and so do their targets;
        their staged outputs are removed."""
        stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        reason = f"interrupted: the server stopped while this job was active (restart at {stamp})"
        ids = self.jobs.recover(reason)
        mark_interrupted(self.db, ids, reason, self.frames_on_disk)
        recover_pending(self.db, self.store.root / "poses")  # maps cut off before durable
        self.store.clear_tmp()  # staging of jobs that were cut off (never committed)

    def frames_on_disk(self, pose_id: str) -> int:
        """How many plan frames of a captured pose are stored (what a resume keeps)."""
        return len(stored_indices(self.store.dir_for(pose_id, create=False)))

    def close(self) -> None:
        """Stop live jobs (stored `interrupted`), make committed maps durable, stop the
        executor's workers, close the rigs and the database.

        Every step runs even when an earlier one failed (logged): a worker or manager process
        that died first must not leave the rigs' devices or the database open."""
        steps: tuple[tuple[str, Callable[[], object]], ...] = (
            ("stopping the jobs", self.jobs.shutdown),
            ("making maps durable", self.maps_sync.drain),
            ("stopping the executor", lambda: self.executor.shutdown(wait=False)),
            ("closing the rigs", self.rigs.close),
            ("closing the database", self.db.close),
        )
        for what, step in steps:
            try:
                step()
            except Exception:
                log.exception("shutdown: %s failed; going on", what)


def get_services(request: Request) -> Services:
    """FastAPI dependency: the app's `Services`."""
    return request.app.state.services
