"""A full disk is a state, not a crash: a service whose data directory lives on a small
tmpfs captures until something fills the disk mid-capture; that capture ends `failed` with
a reason naming the space, nothing stored earlier changes, a new capture is refused with
507 up front, `/health` says degraded, DELETE frees space and the cut-off pose resumes.
No request answers 500 on the way."""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import sqlite3
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.exc import OperationalError

from api.app import create_app
from api.config import ServiceConfig
from api.problems import Problem
from api.storage import DiskSpace, is_no_space
from tests.api.test_api_session import screen_poses, small_rig

MiB = 1 << 20


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 40 MiB tmpfs mounted for the test (needs root, as CI and the dev machines run)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    why = None
    if os.geteuid() != 0 or shutil.which("mount") is None:
        why = "mounting a small tmpfs needs root"
    else:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=40m", "tmpfs", str(mount)],
                              capture_output=True, text=True, check=False)
        if done.returncode != 0:
            why = f"cannot mount a tmpfs here: {done.stderr.strip()}"
    if why is not None:
        if os.environ.get("CI"):  # CI runs as root: a skip there would hide the full disk
            pytest.fail(why)
        pytest.skip(why)
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def fill(path: Path) -> int:
    """Take every free byte of `path`'s filesystem with one file; how many it took."""
    taken = 0
    with open(path, "wb") as fh:
        step = 4 * MiB
        while step >= 4096:
            try:
                os.posix_fallocate(fh.fileno(), taken, step)
                taken += step
            except OSError as exc:
                assert exc.errno == errno.ENOSPC
                step //= 2
    return taken


def wait(c: TestClient, job_id: str, cond, timeout_s: float = 300) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        r = c.get(f"/jobs/{job_id}")
        assert r.status_code == 200, r.text
        if cond(r.json()):
            return r.json()
        time.sleep(0.02)
    raise AssertionError(f"job {job_id}: condition not reached")


def over(j: dict) -> bool:
    return j["status"] not in ("queued", "running")


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_capture_until_the_disk_is_full_then_free_space_and_resume(small_disk: Path) -> None:
    data = small_disk / "data"
    config = ServiceConfig(data_dir=data, executor="threads", space_reserve_bytes=2 * MiB,
                           min_free_bytes=1 * MiB)
    statuses: list[int] = []
    with TestClient(create_app(config)) as c:
        c.event_hooks["response"] = [lambda r: statuses.append(r.status_code)]
        assert (data / "space.reserve").stat().st_size == 2 * MiB
        health = c.get("/health").json()
        assert health["status"] == "ok" and health["storage"]["reserve_held"]
        rig = c.post("/rigs", json={"name": "slow", "config": small_rig(slow=True)}).json()
        sess = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()
        poses = screen_poses(4, 11)

        ready = []
        for k in range(3):
            job = c.post(f"/sessions/{sess['id']}/poses", json={"screen_pose": poses[k]}).json()
            final = wait(c, job["id"], over)
            assert final["status"] == "succeeded", final["error"]
            ready.append(final["resource"].rsplit("/", 1)[1])
        kept = {p: sha(data / "poses" / p / "maps.npz") for p in ready}

        # something else fills the disk while a capture runs: its frames were allocated whole
        # at the first frame, so it is the maps' write that finds no space
        job = c.post(f"/sessions/{sess['id']}/poses", json={"screen_pose": poses[3]}).json()
        wait(c, job["id"], lambda j: j["stage"] == "capture" and j["done"] >= 2)
        filler = small_disk / "filler.bin"
        assert fill(filler) > 0
        final = wait(c, job["id"], over)
        assert final["status"] == "failed"
        assert final["error"].startswith("no space left on device"), final["error"]
        cut = final["resource"].rsplit("/", 1)[1]
        pose = c.get(final["resource"]).json()
        assert pose["status"] == "interrupted" and "no space" in pose["error"]

        # refused up front, with the numbers; health says why it is degraded
        refused = c.post(f"/sessions/{sess['id']}/poses", json={"screen_pose": poses[0]})
        assert refused.status_code == 507, refused.text
        body = refused.json()
        assert body["needed_bytes"] > body["free_bytes"] and "free" in body["detail"]
        health = c.get("/health").json()
        assert health["status"] == "degraded" and "space" in health["reasons"][0]
        assert c.post(f"/sessions/{sess['id']}/poses/{cut}/resume").status_code == 507

        # the claim was released: DELETE works on the full disk and frees space
        for p in ready[1:]:
            assert c.delete(f"/sessions/{sess['id']}/poses/{p}").status_code == 204
            assert not (data / "poses" / p).exists()
        resumed = c.post(f"/sessions/{sess['id']}/poses/{cut}/resume")
        assert resumed.status_code == 202, resumed.text
        again = wait(c, resumed.json()["id"], over)
        assert again["status"] == "succeeded", again["error"]
        assert again["result"]["capture"]["captured"] == 0  # every frame had been kept
        assert c.get(f"/sessions/{sess['id']}/poses/{cut}").json()["status"] == "ready"
        assert sha(data / "poses" / ready[0] / "maps.npz") == kept[ready[0]]
        assert c.get(f"/sessions/{sess['id']}/poses").status_code == 200
    assert statuses and all(s < 500 or s == 507 for s in statuses), statuses


def test_no_space_is_recognised_however_it_is_raised() -> None:
    assert is_no_space(OSError(errno.ENOSPC, "No space left on device"))
    assert is_no_space(OSError(errno.EDQUOT, "Disk quota exceeded"))
    full = sqlite3.OperationalError("database or disk is full")
    assert is_no_space(OperationalError("INSERT", {}, full))
    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError as inner:
            raise RuntimeError("decode failed") from inner
    except RuntimeError as outer:
        assert is_no_space(outer)
    assert is_no_space(RuntimeError("OSError: [Errno 28] No space left on device"))  # a worker's
    assert not is_no_space(OSError(errno.EACCES, "Permission denied"))
    assert not is_no_space(ValueError("bad plan"))


def test_a_request_that_meets_a_full_disk_gets_507_and_the_reserve_is_freed(tmp_path) -> None:
    config = ServiceConfig(data_dir=tmp_path / "data", executor="threads",
                           space_reserve_bytes=1 * MiB, min_free_bytes=1 * MiB)
    app = create_app(config)

    def full() -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    app.add_api_route("/test-full-disk", full, methods=["POST"])
    with TestClient(app) as c:
        assert (tmp_path / "data" / "space.reserve").is_file()
        r = c.post("/test-full-disk")
        assert r.status_code == 507 and r.headers["content-type"] == "application/problem+json"
        body = r.json()
        assert body["title"] == "Insufficient storage" and "no space left" in body["detail"]
        assert not (tmp_path / "data" / "space.reserve").exists()  # the database may use it
        assert c.get("/health").status_code == 200  # same connection, still served


def test_a_released_reserve_still_counts_as_the_databases(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Whether a request fits must not depend on whether some write happened to release the
    reserve (its bytes then show as free on the disk until it is taken back)."""
    space = DiskSpace(tmp_path, reserve_bytes=2 * MiB, margin_bytes=1 * MiB)
    assert space.reserve_held()
    disk = {"free": int(2.5 * MiB)}
    monkeypatch.setattr(space, "free_bytes", lambda: disk["free"])
    fits, too_big = int(1.5 * MiB), int(1.5 * MiB) + 1  # + the 1 MiB margin vs 2.5 MiB
    space.require(fits, "a capture")
    with pytest.raises(Problem) as held:
        space.require(too_big, "a capture")
    assert held.value.status == 507
    assert space.release()
    disk["free"] += 2 * MiB  # the reserve's bytes show as free on the disk
    space.require(fits, "a capture")
    with pytest.raises(Problem) as released:
        space.require(too_big, "a capture")
    assert released.value.status == 507 and released.value.extra["free_bytes"] == 2.5 * MiB
