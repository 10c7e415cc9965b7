"""Live capture through the service: `phasecal serve` over HTTP, a simulated rig at 60 Hz.

Run: .venv/bin/python benchmarks/service_capture.py [--sizes 640x480,2448x2048] [--poses N]
The rig runs on the real clock (60 Hz display, software-triggered 8-bit camera with a
6 DN black level, so dark pattern phases do not clip at 0 DN) and
replays frames it rendered before: one untimed pose fills the simulated camera's replay
cache, so the timed poses measure the service (controller, frame store, streaming decode
in a worker process, job bookkeeping), not the simulator's renderer. Per pose it prints
the capture time against the vsync floor (plan frames / 60 Hz), the time spent storing
frames, and how long after the last frame the pose was ready (job succeeded, maps
committed). Last line: `service capture: worst R x vsync floor; pose ready S s after the
last frame` (S at the largest size).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
REFRESH_HZ = 60.0


def start_server(data: Path) -> tuple[subprocess.Popen, str]:
    """`phasecal serve` (default executor: worker processes) on a free loopback port."""
    sys.path.insert(0, str(ROOT))
    from api.inprocess import free_port

    port = free_port()
    env = dict(os.environ, PHASECAL_DATA_DIR=str(data))
    env.pop("PHASECAL_DASK", None)
    log = open(data.parent / "server.log", "ab")
    proc = subprocess.Popen([sys.executable, "-m", "api.cli", "serve", "--port", str(port)],
                            cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    for _ in range(600):
        try:
            if httpx.get(f"{url}/health", timeout=1).status_code == 200:
                return proc, url
        except httpx.TransportError:
            time.sleep(0.1)
    proc.kill()
    raise SystemExit("server did not start")


def rig_config(width: int, height: int) -> dict:
    return {"kind": "simulated", "clock": "real",
            "display": {"refresh_hz": REFRESH_HZ},
            "camera": {"model": "mild_pinhole", "width": width, "height": height,
                       "bit_depth": 8, "black_level_dn": 6, "replay": True,
                       "max_frame_rate_hz": 240.0},
            "settings": {"exposure_s": 0.004, "pixel_format": "Mono8",
                         "trigger_mode": "software"}}


def capture(c: httpx.Client, session: str) -> tuple[dict, float]:
    """One pose: the finished job and the client's wall time from POST to succeeded."""
    t0 = time.time()
    job = c.post(f"/sessions/{session}/poses", json={}).raise_for_status().json()
    while True:
        j = c.get(f"/jobs/{job['id']}").json()
        if j["status"] not in ("queued", "running"):
            break
        time.sleep(0.01)
    if j["status"] != "succeeded":
        raise SystemExit(f"capture failed: {j['error']}")
    return j, time.time() - t0


def bench_size(c: httpx.Client, width: int, height: int, poses: int) -> list[dict]:
    rig = c.post("/rigs", json={"name": f"bench{width}", "config": rig_config(width, height)})
    rig_id = rig.raise_for_status().json()["id"]
    sess = c.post("/sessions", json={"rig_id": rig_id, "preset": "default"}).json()
    capture(c, sess["id"])  # fills the replay cache, measures the display latency
    rows = []
    for _ in range(poses):
        job, client_s = capture(c, sess["id"])
        cap, dec = job["result"]["capture"], job["result"]["decode"]
        floor = sess["frame_count"] / REFRESH_HZ
        rows.append({"size": f"{width}x{height}", "frames": sess["frame_count"],
                     "floor_s": floor, "capture_s": cap["capture_s"],
                     "ratio": cap["capture_s"] / floor, "store_s": cap["store_s"],
                     "recaptures": cap["recaptures"], "finish_s": dec["wall_s"],
                     "ready_s": job["finished_at"] - cap["captured_at"],
                     "client_s": client_s, "valid": dec["valid_pixels"]})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="640x480,2448x2048")
    ap.add_argument("--poses", type=int, default=2)
    args = ap.parse_args()
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    with tempfile.TemporaryDirectory(prefix="phasecal-bench-") as tmp:
        data = Path(tmp) / "data"
        proc, url = start_server(data)
        try:
            with httpx.Client(base_url=url, timeout=60) as c:
                rows = [r for w, h in sizes for r in bench_size(c, w, h, args.poses)]
        finally:
            proc.terminate()
            proc.wait(30)
    print(f"service capture benchmark: phasecal serve (worker processes), simulated rig at "
          f"{REFRESH_HZ:g} Hz replaying pre-rendered frames; load {os.getloadavg()[0]:.2f} "
          f"on {os.cpu_count()} CPUs")
    head = (f"{'camera':>10s} {'frames':>6s} {'floor s':>8s} {'capture s':>9s} {'R':>5s} "
            f"{'store s':>8s} {'recapt':>6s} {'finish s':>8s} {'ready S':>8s} {'client s':>8s} "
            f"{'valid px':>9s}")
    print(head)
    for r in rows:
        print(f"{r['size']:>10s} {r['frames']:6d} {r['floor_s']:8.2f} {r['capture_s']:9.2f} "
              f"{r['ratio']:5.2f} {r['store_s']:8.3f} {r['recaptures']:6d} {r['finish_s']:8.2f} "
              f"{r['ready_s']:8.2f} {r['client_s']:8.2f} {r['valid']:9d}")
    worst = max(r["ratio"] for r in rows)
    largest = max(rows, key=lambda r: r["frames"] * int(r["size"].split("x")[0]))["size"]
    ready = max(r["ready_s"] for r in rows if r["size"] == largest)
    print(f"service capture: worst {worst:.2f} x vsync floor; pose ready {ready:.2f} s after "
          "the last frame")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
