"""Live capture through the service: `phasecal serve` over HTTP, a simulated rig at 60 Hz.

Run: .venv/bin/python benchmarks/service_capture.py [--sizes 640x480,2448x2048] [--poses N]
[--library] (`--library`: also the library's finish on the largest size's last pose, same
frames, this process)
The rig runs on the real clock (60 Hz display with 2 frames of input latency,
software-triggered 8-bit camera with a 4 ms exposure and a 6 DN black level, so dark
pattern phases do not clip at 0 DN) and replays frames it rendered before: one untimed
pose fills the simulated camera's replay cache, so the timed poses measure the service
(controller, frame store, streaming decode in a worker process, job bookkeeping), not the
simulator's renderer.

R is the capture time over the vsync floor of the plan (benchmarks/acquisition_timing.py,
docs/physics.md section 7): L + P + N * ceil((P + e) / P) * P for N plan frames, refresh period
P, latency L, exposure e. A global-shutter exposure sees one pattern on every row only
while that pattern is held through a full scan-out, so each pattern needs two refreshes
when e > 0; the integrity repeats at the end of the pose (3 frames) and everything else
the service does count against R. `x N*P` is the same time over N refresh periods (no
camera can reach 1.0 there). Capture time is taken both ways: `server` is the job's
controller run (`capture_s`: camera set-up, plan frames, integrity repeats and check);
`client` is from the POST to the last stored plan frame (same clock, same machine). S is
the time from the last stored plan frame to the job's success as the client sees it (its
`end` server-sent event: maps written and committed).
`recap` counts the patterns shown again (torn frames), `late ms` is the latest any trigger
fired after its planned time (a stall of the machine: beyond the exposure window's slack,
~9 ms here, it tears that pattern; docs/acquisition.md). `stall ms` is the longest
oversleep of a separate plain process sleeping 2 ms in a loop during the same capture
(benchmarks/stall_probe.py): a `late ms` about that size is the machine's stall, not the
service's; `steal ms` is the hypervisor's steal time over the pose (all CPUs, Linux guests).
Per pose the server-side stages after the last frame are printed: `tail` (controller: the
integrity repeats and check), `close` (the frame store's last copies and final fsync, in
the server while the worker finishes), `lag` (decode worker catching up with the last frame),
`finish` (decoder finish; `fin cpu` its CPU seconds, all worker threads; the decoder writes
into the maps file laid out before the first frame, `pf` the share of its pages faulted in
while frames arrived), `write` (CRC-32s, headers, meta, rename of the maps NPZ in the page
cache; `wr cpu`), `hand` (from the worker's end of the write to the server holding its
result: the task's return, the result's trip between processes), `commit` (durable mark,
rename into the pose; the fsync of the maps runs after the pose is ready,
api/maps_durability.py), `job` (from the commit to the job's recorded end);
and the CPU seconds the pose cost the server process (`api cpu`: HTTP, job, controller,
frame store) and its worker processes (`wkr cpu`: streaming decode, maps write).
Last line: `service capture: worst R x vsync floor; pose ready S s after the last frame`
(worst client-side R over all poses, worst S at the largest size).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
from stall_probe import StallProbe, steal_ms

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


EXPOSURE_S = 0.004
LATENCY_PERIODS = 2


def rig_config(width: int, height: int) -> dict:
    return {"kind": "simulated", "clock": "real",
            "display": {"refresh_hz": REFRESH_HZ, "latency_periods": LATENCY_PERIODS},
            "camera": {"model": "mild_pinhole", "width": width, "height": height,
                       "bit_depth": 8, "black_level_dn": 6, "replay": True,
                       "max_frame_rate_hz": 240.0},
            "settings": {"exposure_s": EXPOSURE_S, "pixel_format": "Mono8",
                         "trigger_mode": "software"}}


def vsync_floor(frames: int) -> float:
    """L + P + N * ceil((P + e) / P) * P (benchmarks/acquisition_timing.py)."""
    p = 1.0 / REFRESH_HZ
    return LATENCY_PERIODS * p + p + frames * math.ceil((p + EXPOSURE_S) / p - 1e-9) * p


def capture(c: httpx.Client, session: str) -> tuple[dict, float, float]:
    """One pose: the finished job, the client's POST time and when it learnt the job ended.

    The client follows the job's server-sent events (`GET /jobs/{id}/events`) to its `end`
    event, as a live client would; polling `GET /jobs/{id}` every few ms instead costs the
    server a request per poll on the cores the capture uses.
    """
    t0 = time.time()
    job = c.post(f"/sessions/{session}/poses", json={}).raise_for_status().json()
    final: dict | None = None
    with c.stream("GET", f"/jobs/{job['id']}/events", timeout=600) as events:
        event = ""
        for line in events.iter_lines():
            if line.startswith("event: "):
                event = line[len("event: "):]
            elif line.startswith("data: ") and event == "end":
                final = json.loads(line[len("data: "):])
                break
    seen = time.time()
    if final is None or final["status"] != "succeeded":
        raise SystemExit(f"capture failed: {final and final['error']}")
    return final, t0, seen


def cpu_seconds(pid: int) -> tuple[float, float]:
    """CPU seconds (user + system) used so far by the server process and by its children
    (the worker processes that decode): stable figures on a loaded machine."""
    import psutil

    def used(p: psutil.Process) -> float:
        t = p.cpu_times()
        return t.user + t.system

    server = psutil.Process(pid)
    workers = 0.0
    for child in server.children(recursive=True):
        try:
            workers += used(child)
        except psutil.NoSuchProcess:
            pass
    return used(server), workers


def bench_size(c: httpx.Client, pid: int, width: int, height: int, poses: int,
               probe: StallProbe) -> list[dict]:
    rig = c.post("/rigs", json={"name": f"bench{width}", "config": rig_config(width, height)})
    rig_id = rig.raise_for_status().json()["id"]
    sess = c.post("/sessions", json={"rig_id": rig_id, "preset": "default"}).json()
    capture(c, sess["id"])  # fills the replay cache, measures the display latency
    rows = []
    for _ in range(poses):
        load = os.getloadavg()[0]
        api0, workers0 = cpu_seconds(pid)
        steal0 = steal_ms()
        job, posted, seen = capture(c, sess["id"])
        steal1 = steal_ms()
        api1, workers1 = cpu_seconds(pid)
        cap, dec = job["result"]["capture"], job["result"]["decode"]
        n = sess["frame_count"]
        floor, last = vsync_floor(n), cap["captured_at"]
        rows.append({"size": f"{width}x{height}", "frames": n, "floor_s": floor,
                     "capture_s": cap["capture_s"], "client_cap_s": last - posted,
                     "ratio": cap["capture_s"] / floor, "client_ratio": (last - posted) / floor,
                     "np_ratio": (last - posted) * REFRESH_HZ / n,
                     "store_s": cap["store_s"], "recaptures": cap["recaptures"],
                     "late_ms": 1e3 * cap["trigger_late_s"],
                     "stall_ms": probe.worst_ms(posted, last),
                     "steal_ms": math.nan if steal0 is None else steal1 - steal0,
                     "tail_s": cap["controller_done_at"] - last, "close_s": cap["close_s"],
                     "lag_s": dec["caught_up_at"] - last, "finish_s": dec["finish_s"],
                     "finish_cpu": dec["finish_cpu_s"], "write_cpu": dec["write_cpu_s"],
                     "write_s": dec["write_s"], "commit_s": dec["commit_s"],
                     "prefaulted": dec["prefaulted"],
                     "handoff_s": dec["decoded_at"] - dec["caught_up_at"] - dec["finish_s"]
                     - dec["write_s"],
                     "job_s": job["finished_at"] - dec["decoded_at"] - dec["commit_s"],
                     "server_ready_s": job["finished_at"] - last, "ready_s": seen - last,
                     "api_cpu": api1 - api0, "worker_cpu": workers1 - workers0,
                     "valid": dec["valid_pixels"], "load": load,
                     "pose": job["resource"].rsplit("/", 1)[1], "session": sess["id"]})
    return rows


def library_finish(data: Path, row: dict) -> dict:
    """The same pose's stored frames decoded in this process as the live worker does (add
    per period group, then finish, noise from residuals): the library's finish on identical
    frames at the same load, to compare with the service's `finish` / `fin cpu`."""
    import numpy as np

    from calibration.decode import StreamingDecoder
    from calibration.shared.plan import read_plan

    plan = read_plan(data / "sessions" / row["session"] / "plan.json")
    frames = np.load(data / "poses" / row["pose"] / "frames.npy", mmap_mode="r")
    best = {"finish_s": math.inf}
    for _ in range(2):
        dec = StreamingDecoder(plan, frames.shape[1:])
        dec.prepare()
        left = list(range(frames.shape[0]))
        while left:
            ready = dec.ready_frames(left)
            dec.add_frames(ready, frames, rows=ready)
            left = [i for i in left if i not in ready]
        t0, c0 = time.perf_counter(), time.process_time()
        dec.finish()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        if wall < best["finish_s"]:
            best = {"finish_s": wall, "finish_cpu": cpu}
    return best


COLUMNS = [  # header, row key, width, format
    ("camera", "size", 10, "s"), ("frames", "frames", 6, "d"), ("floor s", "floor_s", 7, ".3f"),
    ("cap s", "capture_s", 6, ".2f"), ("R", "ratio", 5, ".2f"),
    ("client s", "client_cap_s", 8, ".2f"), ("R cl", "client_ratio", 5, ".2f"),
    ("x N*P", "np_ratio", 5, ".2f"), ("store s", "store_s", 7, ".3f"),
    ("recap", "recaptures", 5, "d"), ("late ms", "late_ms", 7, ".1f"),
    ("stall ms", "stall_ms", 8, ".1f"), ("steal ms", "steal_ms", 8, ".0f"),
    ("tail s", "tail_s", 6, ".2f"),
    ("close", "close_s", 5, ".2f"), ("lag s", "lag_s", 6, ".2f"),
    ("finish", "finish_s", 6, ".2f"), ("fin cpu", "finish_cpu", 7, ".2f"),
    ("pf", "prefaulted", 4, ".2f"), ("write", "write_s", 6, ".2f"),
    ("wr cpu", "write_cpu", 6, ".2f"),
    ("hand", "handoff_s", 5, ".2f"), ("commit", "commit_s", 6, ".3f"),
    ("job", "job_s", 5, ".2f"), ("S srv", "server_ready_s", 6, ".2f"),
    ("S", "ready_s", 6, ".2f"), ("api cpu", "api_cpu", 7, ".2f"),
    ("wkr cpu", "worker_cpu", 7, ".2f"), ("valid px", "valid", 9, "d"), ("load", "load", 5, ".1f")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="640x480,2448x2048")
    ap.add_argument("--poses", type=int, default=2)
    ap.add_argument("--library", action="store_true",
                    help="also decode the largest size's last pose in this process (same frames)")
    args = ap.parse_args()
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    with tempfile.TemporaryDirectory(prefix="phasecal-bench-") as tmp:
        data = Path(tmp) / "data"
        proc, url = start_server(data)
        probe = StallProbe()
        try:
            with httpx.Client(base_url=url, timeout=60) as c:
                rows = [r for w, h in sizes
                        for r in bench_size(c, proc.pid, w, h, args.poses, probe)]
        finally:
            probe.close()
            proc.terminate()
            proc.wait(30)
        lib = library_finish(data, rows[-1]) if args.library else None
    print(f"service capture benchmark: phasecal serve (worker processes), simulated rig at "
          f"{REFRESH_HZ:g} Hz replaying pre-rendered frames; load {os.getloadavg()[0]:.2f} "
          f"on {os.cpu_count()} CPUs (`load`: 1-min average before each pose)")
    print(" ".join(f"{name:>{width}s}" for name, _, width, _ in COLUMNS))
    for r in rows:
        print(" ".join(f"{r[key]:>{width}{spec}}" for _, key, width, spec in COLUMNS))
    worst = max(max(r["ratio"], r["client_ratio"]) for r in rows)
    largest = max(rows, key=lambda r: r["frames"] * int(r["size"].split("x")[0]))["size"]
    ready = max(r["ready_s"] for r in rows if r["size"] == largest)
    if lib is not None:
        r = rows[-1]
        print(f"library finish on the same frames ({r['size']}, last pose, this process, best "
              f"of 2): {lib['finish_s']:.2f} s wall, {lib['finish_cpu']:.2f} CPU s; service: "
              f"{r['finish_s']:.2f} s wall, {r['finish_cpu']:.2f} CPU s "
              f"({r['finish_cpu'] / lib['finish_cpu']:.2f}x the library's CPU)")
    print(f"service capture: worst {worst:.2f} x vsync floor; pose ready {ready:.2f} s after "
          "the last frame")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
