"""The data directory: safe ids -> paths, atomic file writes, per-resource folders.

No path from a request reaches the filesystem unchecked: every id is matched against
`ID_RE` and every resolved path is checked to lie inside the data directory.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from api.problems import Problem
from calibration.shared.atomic import write_bytes_atomic

ID_RE = re.compile(r"^(rig|ses|pose|cal|job)_[0-9a-f]{16}$")
KIND_DIRS = {"ses": "sessions", "pose": "poses", "cal": "calibrations", "rig": "rigs"}


def new_id(prefix: str) -> str:
    """A fresh random id such as `ses_0123456789abcdef`."""
    if prefix not in ("rig", "ses", "pose", "cal", "job"):
        raise ValueError(f"unknown id prefix {prefix!r}")
    return f"{prefix}_{secrets.token_hex(8)}"


def check_id(ident: str, prefix: str, kind: str) -> str:
    """Return `ident` if it is a well-formed id of `prefix`; else a 404 problem."""
    if not ID_RE.match(ident) or not ident.startswith(prefix + "_"):
        raise Problem(404, "not-found", f"{kind} {ident!r} does not exist (malformed id)")
    return ident


class DataStore:
    """Owns the data directory layout; all writes are temp-file-then-rename."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        (self.root / "tmp").mkdir(exist_ok=True)

    @property
    def db_path(self) -> Path:
        """The SQLite database file."""
        return self.root / "phasecal.db"

    def dir_for(self, ident: str, create: bool = True) -> Path:
        """The folder of a resource (`sessions/<id>`, `poses/<id>`, `calibrations/<id>`)."""
        if not ID_RE.match(ident):
            raise Problem(404, "not-found", f"{ident!r} is not a valid resource id")
        sub = KIND_DIRS.get(ident.split("_", 1)[0])
        if sub is None:
            raise Problem(404, "not-found", f"{ident!r} has no stored files")
        path = (self.root / sub / ident).resolve()
        if self.root not in path.parents:
            raise Problem(404, "not-found", f"{ident!r} resolves outside the data directory")
        if create:
            path.mkdir(parents=True, exist_ok=True)
        return path

    def file(self, ident: str, name: str) -> Path:
        """A file inside a resource folder; `name` must be a plain file name."""
        if not re.fullmatch(r"[A-Za-z0-9_.-]{1,64}", name) or name.startswith("."):
            raise Problem(404, "not-found", f"{name!r} is not a valid file name")
        return self.dir_for(ident) / name

    def write_bytes(self, path: Path, data: bytes) -> None:
        """Write bytes atomically (fsync, then rename over the target)."""
        write_bytes_atomic(path, data)

    def temp_dir(self) -> Path:
        """A fresh scratch folder inside the data directory (same filesystem: renames work)."""
        return Path(tempfile.mkdtemp(dir=self.root / "tmp"))

    @contextmanager
    def staging(self, job_id: str) -> Iterator[Path]:
        """A job-owned folder for a worker's outputs, removed when the job ends.

        Workers write only here; the owning server moves finished files into place
        (`commit`), so a worker that outlives its server never touches a resource folder.
        """
        if not ID_RE.match(job_id) or not job_id.startswith("job_"):
            raise ValueError(f"{job_id!r} is not a job id")
        path = self.root / "tmp" / job_id
        path.mkdir(parents=True, exist_ok=True)
        try:
            yield path
        finally:
            shutil.rmtree(path, ignore_errors=True)

    def commit(self, staged: Path, names: Iterable[str], dest: Path) -> None:
        """Move the named finished files from a staging folder into `dest` (renames)."""
        dest.mkdir(parents=True, exist_ok=True)
        for name in names:
            os.replace(staged / name, dest / name)

    def clear_tmp(self) -> int:
        """Remove stale scratch and staging left by an earlier process; returns how many."""
        tmp = self.root / "tmp"
        stale = list(tmp.iterdir())
        for p in stale:
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
        return len(stale)

    def replace_dir(self, src: Path, dst: Path) -> None:
        """Move a fully written file or folder into place, replacing any previous one."""
        if dst.is_dir():
            shutil.rmtree(dst)
        os.replace(src, dst)
