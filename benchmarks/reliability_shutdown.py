"""Stopping `phasecal serve` with a signal in the middle of a capture, the three ways an
operator does: SIGTERM to the server alone (`kill PID`, systemd with KillMode=mixed),
SIGTERM to every process of the service (systemd's default KillMode=control-group) and
SIGINT to the whole process group (a terminal's Ctrl-C). The server runs the default
executor (worker processes) on a simulated rig.

Per signal: the exit code, seconds from the signal to the exit, processes of the server
left running, the capture job and its pose as stored in the database, whether the log has
a traceback or "shutdown failed"; `held` when it exited 0 with a clean log, no process
left, and job and pose stored `interrupted` with a reason. `benchmarks/reliability.py`
prints the rows.

    .venv/bin/python benchmarks/reliability_shutdown.py
"""

from __future__ import annotations

import os
import signal
import sqlite3
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from api.demo import demo_rig_config  # noqa: E402
from benchmarks.serve_process import descendants, running, start_serve  # noqa: E402
from calibration.shared.plan import ScreenGeometry  # noqa: E402

#: label -> (signal, sent to the server's whole process group)
CASES: dict[str, tuple[signal.Signals, bool]] = {
    "SIGTERM to the server": (signal.SIGTERM, False),
    "SIGTERM to the process group": (signal.SIGTERM, True),
    "SIGINT to the process group (Ctrl-C)": (signal.SIGINT, True),
}
FRAMES_BEFORE_SIGNAL = 3


def capture_midway(url: str) -> dict[str, Any]:
    """Start a capture on a slow simulated rig (4x supersampled rendering) and return its
    job once `FRAMES_BEFORE_SIGNAL` frames are in."""
    screen = ScreenGeometry(320, 240, (0.5, 0.5))
    cfg = demo_rig_config(320, 240, camera="mild_pinhole", screen=screen)
    cfg["camera"]["supersample"] = 4
    with httpx.Client(base_url=url, timeout=60) as c:
        rig = c.post("/rigs", json={"name": "slow", "config": cfg}).json()
        sess = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()
        pose = {"rvec": [0.0, 0.0, 0.0], "tvec_mm": [-80.0, -60.0, 250.0]}
        job = c.post(f"/sessions/{sess['id']}/poses", json={"screen_pose": pose}).json()
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            j = c.get(f"/jobs/{job['id']}").json()
            if j["done"] >= FRAMES_BEFORE_SIGNAL or j["status"] != "running":
                return j
            time.sleep(0.05)
    raise RuntimeError("the capture did not start")


def stored(db_path: Path, table: str, ident: str) -> tuple[str | None, str | None]:
    """(status, error) of one row as the database file holds it."""
    with sqlite3.connect(db_path) as db:
        row = db.execute(f"SELECT status, error FROM {table} WHERE id = ?", (ident,)).fetchone()
    return (row[0], row[1]) if row else (None, None)


def shutdown_case(label: str, sig: signal.Signals, group: bool, tmp: Path) -> dict[str, Any]:
    """One signal to a server mid-capture: what an operator would check afterwards."""
    data, log = tmp / "data", tmp / "serve.log"
    proc, url = start_serve(data, log=log, new_session=True)
    try:
        job = capture_midway(url)
        children = descendants(proc.pid)
        t0 = time.monotonic()
        if group:
            os.killpg(proc.pid, sig)
        else:
            proc.send_signal(sig)
        proc.wait(120)
        exit_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(30)
    deadline = time.monotonic() + 5
    while running(children) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = running(children)
    for p in left:  # leave nothing behind on the lab machine
        os.kill(p, signal.SIGKILL)
    text = log.read_text()
    clean_log = "Traceback" not in text and "shutdown failed" not in text.lower()
    pose_id = str(job["resource"]).rsplit("/", 1)[-1]
    job_status, job_error = stored(data / "phasecal.db", "jobs", job["id"])
    pose_status, pose_error = stored(data / "phasecal.db", "poses", pose_id)
    held = (proc.returncode == 0 and clean_log and not left
            and job_status == pose_status == "interrupted"
            and bool(job_error) and bool(pose_error))
    return {"signal": label, "exit code": proc.returncode, "seconds to exit": round(exit_s, 2),
            "orphans": len(left), "job status after": job_status, "pose status after":
            pose_status, "reason": job_error, "clean log": clean_log, "held": held}


def run_shutdown_cases() -> list[dict[str, Any]]:
    """One row per signal (see the module's doc), each on a fresh server and data folder."""
    rows = []
    for label, (sig, group) in CASES.items():
        with tempfile.TemporaryDirectory(prefix="phasecal-shutdown-") as tmp:
            rows.append(shutdown_case(label, sig, group, Path(tmp)))
    return rows


def main() -> int:
    rows = run_shutdown_cases()
    cols = ("signal", "exit code", "seconds to exit", "orphans", "job status after",
            "pose status after", "clean log", "held")
    widths = [max(len(c), *(len(str(r[c])) for r in rows)) for c in cols]
    print(f"shutdown on a signal mid-capture (cpus {os.cpu_count()}, "
          f"load {os.getloadavg()[0]:.1f})")
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths, strict=True)))
    for r in rows:
        print("  ".join(str(r[c]).ljust(w) for c, w in zip(cols, widths, strict=True)))
    for r in rows:
        print(f"{r['signal']}: {r['reason']}")
    return 0 if all(r["held"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
