"""Rigs of the service: records in SQLite, opened lazily through `acquisition.rig`.

A rig is opened once per process and shared; its lock serializes captures and
settings changes (one screen, and one camera or several captured together).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from sqlalchemy import select

from acquisition.errors import AcquisitionError
from acquisition.rig import RigConfigError, load_rig_config, open_rig
from acquisition.rig import parse_rig_config as parse_acquisition_rig_config
from api.db import Database, RigRecord
from api.problems import Problem
from api.rig_policy import check_client_rig
from api.store import check_id, new_id
from hw_mocks.rig import open_simulated_rig

if TYPE_CHECKING:
    from acquisition.protocols import SimulatorControls
    from acquisition.rig import Rig

log = logging.getLogger("phasecal.rigs")
DEFAULT_RIG_NAME = "default"


@dataclass
class RigHandle:
    """An opened rig (`acquisition.rig.Rig`) and the lock that serializes its use."""

    rig_id: str
    rig: Rig
    lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def simulated(self) -> SimulatorControls | None:
        """The simulator-only controls of a simulated rig, else None."""
        return self.rig.simulated

    def placeable(self) -> Any:
        """The simulated rig whose screen a request may place: 409 on a real rig, where a
        person or robot moves it, and on a simulated one whose view follows its mover."""
        sim = self.simulated
        if sim is None:
            raise Problem(409, "not-simulated", f"rig {self.rig_id} is not simulated: move the "
                          "screen physically and capture without screen_pose")
        if sim.handeye is not None:  # a placed screen would not be where the mover says
            carried = "camera" if sim.handeye.mount == "eye-in-hand" else "screen"
            raise Problem(409, "view-follows-mover",
                          f"rig {self.rig_id} carries its {carried} on its mover, so the view "
                          "follows the mover: move the mover (an automatic run, POST "
                          "/sessions/{id}/auto) and capture without screen_pose")
        return sim

    def move_screen(self, screen_pose: dict[str, Any]) -> None:
        """Place the simulated screen (`rvec`, `tvec_mm`); 409 where `placeable` refuses."""
        sim = self.placeable()
        rot, _ = cv2.Rodrigues(np.asarray(screen_pose["rvec"], np.float64))
        sim.set_pose(rot, np.asarray(screen_pose["tvec_mm"], np.float64))


def parse_rig_config(config: dict[str, Any], source: str = "rig config") -> Any:
    """Validate a rig config (the TOML/JSON fields) with `acquisition.rig`; 422 on error."""
    try:
        return parse_acquisition_rig_config(config, source)
    except RigConfigError as exc:
        raise Problem(422, "invalid-rig-config", str(exc)) from None


def load_default_config(spec: str) -> dict[str, Any]:
    """`simulated` (the default simulated rig) or a TOML/JSON rig config file -> config data.

    The simulated default is validated when first opened; a file is validated at once so
    that `phasecal serve --rig bad.toml` fails at startup.
    """
    if spec == "simulated":
        return {"kind": "simulated"}

    path = Path(spec)
    if not path.is_file():
        raise ValueError(f"--rig {spec}: no such rig config file (or use 'simulated')")
    return load_rig_config(path).model_dump(mode="json")


def load_rigs_dir(folder: Path) -> dict[str, dict[str, Any]]:
    """Operator rigs of a folder: every `*.toml`/`*.json` file, named by its stem."""
    if not folder.is_dir():
        raise ValueError(f"--rigs-dir {folder}: no such folder")
    files = sorted(p for p in folder.iterdir() if p.suffix in (".toml", ".json"))
    names = [p.stem for p in files]
    if DEFAULT_RIG_NAME in names or len(set(names)) != len(names):
        raise ValueError(f"--rigs-dir {folder}: rig names (file stems) must be unique and not "
                         f"{DEFAULT_RIG_NAME!r}")
    return {p.stem: load_rig_config(p).model_dump(mode="json") for p in files}


class RigManager:
    """Creates rig records, opens rigs on demand and closes them at shutdown."""

    def __init__(self, db: Database, default_spec: str, data_dir: Path,
                 rigs_dir: Path | None = None, aravis_ids: tuple[str, ...] = ()) -> None:
        self.db = db
        self.data_dir = data_dir
        self.aravis_ids = aravis_ids
        self._handles: dict[str, RigHandle] = {}
        self._lock = threading.Lock()
        operator = {DEFAULT_RIG_NAME: load_default_config(default_spec)}
        operator.update(load_rigs_dir(rigs_dir) if rigs_dir is not None else {})
        self.operator_names = frozenset(operator)
        self.default_id = ""
        for name, config in operator.items():
            rid = self._upsert(name, config)
            self.default_id = self.default_id or rid

    def _upsert(self, name: str, config: dict[str, Any]) -> str:
        """Store an operator rig under its name (replacing the config of an earlier run)."""
        with self.db.session() as s:
            rec = s.scalars(select(RigRecord).where(RigRecord.name == name)).first()
            if rec is None:
                rec = RigRecord(id=new_id("rig"), name=name, config=config,
                                created_at=time.time())
                s.add(rec)
            else:
                rec.config = config
            return rec.id

    def create(self, name: str, config: dict[str, Any]) -> RigRecord:
        """Validate, open (so a bad config fails here, not at the first capture) and store.

        Rigs from a request may name only listed devices and recordings inside the data
        directory (`api.rig_policy`); operator rig names are reserved.
        """
        if name in self.operator_names:
            raise Problem(409, "conflict", f"rig name {name!r} is reserved for an operator rig "
                          "(serve --rig / --rigs-dir)")
        parsed = check_client_rig(parse_rig_config(config, "config"), self.data_dir,
                                  aravis_ids=self.aravis_ids)
        rig_id = new_id("rig")
        rig = _open(rig_id, name, parsed)
        with self._lock:
            self._handles[rig_id] = RigHandle(rig_id, rig)
        with self.db.session() as s:
            rec = RigRecord(id=rig_id, name=name, config=parsed.model_dump(mode="json"),
                            created_at=time.time())
            s.add(rec)
        return rec

    def resolve(self, rig_id: str) -> str:
        """The rig id a `/rigs/{id}/...` path names: `default` is the rig the server was
        started with (`--rig`); anything else must be a well-formed rig id (else 404)."""
        if rig_id == DEFAULT_RIG_NAME:
            return self.default_id
        return check_id(rig_id, "rig", "rig")

    def record(self, rig_id: str) -> RigRecord:
        """The stored rig or a 404 problem."""
        with self.db.session() as s:
            rec = s.get(RigRecord, rig_id)
            if rec is None:
                raise Problem(404, "not-found", f"rig {rig_id!r} does not exist")
            return rec

    def handle(self, rig_id: str) -> RigHandle:
        """The opened rig (opening it on first use)."""
        with self._lock:
            h = self._handles.get(rig_id)
            if h is not None:
                return h
        rec = self.record(rig_id)
        parsed = parse_rig_config(rec.config, f"rig {rig_id}")
        if rec.name not in self.operator_names:  # stored by a client (maybe by an older version)

            parsed = check_client_rig(parsed, self.data_dir, aravis_ids=self.aravis_ids)
        rig = _open(rig_id, rec.name, parsed)
        with self._lock:
            h = self._handles.setdefault(rig_id, RigHandle(rig_id, rig))
        if h.rig is not rig:
            rig.close()
        return h

    def close(self) -> None:
        """Close every opened rig (one that fails to close is logged, the others still are)."""
        with self._lock:
            handles, self._handles = list(self._handles.values()), {}
        for h in handles:
            try:
                h.rig.close()
            except Exception:
                log.exception("closing rig %s failed; closing the others", h.rig_id)


def _open(rig_id: str, name: str, config: Any) -> Rig:
    """Open a rig's devices; problems name the rig and say whether config or device failed."""
    try:
        return open_rig(config, simulator=open_simulated_rig)
    except (ValueError, TypeError, KeyError) as exc:
        raise Problem(422, "invalid-rig-config",
                      f"rig {rig_id} ({name}): cannot be opened: {exc}") from None
    except (OSError, AcquisitionError) as exc:
        raise Problem(503, "device-error",
                      f"rig {rig_id} ({name}): a device failed to open: {exc}") from None
