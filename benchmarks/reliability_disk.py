"""A full disk, as a lab server meets it: `phasecal serve` (worker processes) with its data
directory on a small tmpfs captures poses until the service refuses the next one; then a
capture runs while another program takes the rest of the disk. Counted: answers >= 500
other than 507, whether the cut-off capture ended `failed` naming the space with its pose
resumable, whether earlier maps stayed byte-identical, whether DELETE freed space, and
whether the cut-off pose then resumed and a new capture succeeded.

Needs root (it mounts a tmpfs). `benchmarks/reliability.py` prints its row.

    .venv/bin/python benchmarks/reliability_disk.py [--size-mib 48]
"""

from __future__ import annotations

import argparse
import errno
import hashlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acquisition.patterns import build_plan  # noqa: E402
from api.demo import demo_rig_config  # noqa: E402
from benchmarks.serve_process import start_serve  # noqa: E402

MiB = 1 << 20
SCREEN = build_plan(320, 240, 0.5, preset="fast").screen


def slow_rig() -> dict[str, Any]:
    """320x240 with supersampled rendering: a capture lasts long enough to fill the disk
    while it runs."""
    cfg = demo_rig_config(320, 240, camera="mild_pinhole", screen=SCREEN)
    cfg["camera"]["supersample"] = 4
    return cfg


def screen_pose(k: int) -> dict[str, Any]:
    """A distinct, visible screen pose for capture `k`."""
    return {"rvec": [0.05 * (k % 3), -0.04 * (k % 2), 0.0],
            "tvec_mm": [-80.0 + 3 * k, -60.0, 250.0 + 5 * k]}


def fill(path: Path) -> int:
    """Take every free byte of `path`'s filesystem with one file (another program's)."""
    taken, step = 0, 4 * MiB
    with open(path, "wb") as fh:
        while step >= 4096:
            try:
                os.posix_fallocate(fh.fileno(), taken, step)
                taken += step
            except OSError as exc:
                if exc.errno != errno.ENOSPC:
                    raise
                step //= 2
    return taken


class Recorder(httpx.Client):
    """A client that keeps every status code it got (a dropped connection counts as 599)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.codes: list[int] = []

    def request(self, *args: Any, **kwargs: Any) -> httpx.Response:
        try:
            r = super().request(*args, **kwargs)
        except (httpx.RemoteProtocolError, httpx.ReadError):
            r = httpx.Response(599)
        self.codes.append(r.status_code)
        return r


def wait_job(c: Recorder, job_id: str, until: Any, timeout_s: float = 300) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        j = c.get(f"/jobs/{job_id}").json()
        if until(j):
            return j
        time.sleep(0.05)
    raise RuntimeError(f"job {job_id} did not reach its condition")


def over(j: dict[str, Any]) -> bool:
    return j["status"] not in ("queued", "running")


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def scenario(c: Recorder, disk: Path, data: Path) -> dict[str, Any]:
    """The sequence on a running server; the facts the table reports."""
    out: dict[str, Any] = {}
    rig = c.post("/rigs", json={"name": "slow", "config": slow_rig()}).json()
    sid = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()["id"]
    ready: list[str] = []
    refused = None
    for k in range(64):  # until the service refuses the next capture
        r = c.post(f"/sessions/{sid}/poses", json={"screen_pose": screen_pose(k)})
        if r.status_code != 202:
            refused = r
            break
        j = wait_job(c, r.json()["id"], over)
        if j["status"] != "succeeded":
            out["unexpected"] = j["error"]
            return out
        ready.append(j["resource"].rsplit("/", 1)[1])
    out["poses before refusal"] = len(ready)
    out["refusal"] = refused.status_code if refused is not None else None
    kept = {p: digest(data / "poses" / p / "maps.npz") for p in ready}
    # free two poses, then let another program take the disk while a capture runs
    for p in ready[-2:]:
        c.delete(f"/sessions/{sid}/poses/{p}")
    ready = ready[:-2]
    r = c.post(f"/sessions/{sid}/poses", json={"screen_pose": screen_pose(99)})
    job = wait_job(c, r.json()["id"], lambda j: (j["stage"] == "capture" and j["done"] >= 2)
                   or over(j))
    filler = disk / "other-program.bin"
    fill(filler)
    job = wait_job(c, job["id"], over)
    cut = job["resource"].rsplit("/", 1)[1]
    out["cut-off job"] = f"{job['status']}: {(job['error'] or '')[:60]}"
    out["cut-off pose"] = c.get(job["resource"]).json()["status"]
    out["health when full"] = c.get("/health").json()["status"]
    out["capture when full"] = c.post(f"/sessions/{sid}/poses", json={}).status_code
    deleted = [c.delete(f"/sessions/{sid}/poses/{p}").status_code for p in ready[-3:]]
    ready = ready[:-3]
    out["DELETE on full disk"] = deleted
    resumed = c.post(f"/sessions/{sid}/poses/{cut}/resume")
    out["resume after DELETE"] = (wait_job(c, resumed.json()["id"], over)["status"]
                                  if resumed.status_code == 202 else resumed.status_code)
    r = c.post(f"/sessions/{sid}/poses", json={"screen_pose": screen_pose(100)})
    out["next capture"] = (wait_job(c, r.json()["id"], over)["status"]
                           if r.status_code == 202 else r.status_code)
    out["earlier maps changed"] = sum(digest(data / "poses" / p / "maps.npz") != kept[p]
                                      for p in ready)
    filler.unlink()
    return out


def run_disk_case(size_mib: int = 48) -> list[dict[str, Any]]:
    """One row: the full-disk sequence on a `size_mib` tmpfs (skipped without root)."""
    row: dict[str, Any] = {"case": f"data directory on a {size_mib} MiB tmpfs"}
    with tempfile.TemporaryDirectory(prefix="phasecal-disk-") as tmp:
        disk = Path(tmp) / "disk"
        disk.mkdir()
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mib}m", "tmpfs",
                                  str(disk)], capture_output=True, text=True, check=False)
        if mounted.returncode != 0:
            return [{**row, "held": None, "outcome": f"not run: {mounted.stderr.strip()}"}]
        proc = None
        try:
            data = disk / "data"
            env = {"PHASECAL_SPACE_RESERVE_BYTES": str(2 * MiB),
                   "PHASECAL_MIN_FREE_BYTES": str(1 * MiB)}
            proc, url = start_serve(data, env=env)
            with Recorder(base_url=url, timeout=120) as c:
                facts = scenario(c, disk, data)
                errors = [s for s in c.codes if s >= 500 and s != 507]
        finally:
            if proc is not None:
                proc.terminate()
                proc.wait(60)
            subprocess.run(["umount", "-l", str(disk)], check=False)
    held = (not errors and facts.get("refusal") == 507
            and str(facts.get("cut-off job", "")).startswith("failed: no space left")
            and facts.get("cut-off pose") == "interrupted"
            and facts.get("health when full") == "degraded"
            and facts.get("capture when full") == 507
            and all(s == 204 for s in facts.get("DELETE on full disk", [0]))
            and facts.get("resume after DELETE") == "succeeded"
            and facts.get("next capture") == "succeeded"
            and facts.get("earlier maps changed") == 0)
    outcome = ", ".join(f"{k} {v}" for k, v in facts.items())
    return [{**row, "held": held, "server errors": len(errors), "outcome": outcome}]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size-mib", type=int, default=48)
    args = ap.parse_args()
    for row in run_disk_case(args.size_mib):
        print(row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
