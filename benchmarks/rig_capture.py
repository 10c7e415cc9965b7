"""Live capture of a rig of several cameras through the service: `phasecal serve` over HTTP,
one 60 Hz screen, N simulated cameras captured in sync.

Run: .venv/bin/python benchmarks/rig_capture.py [--cameras 4] [--size 2448x2048] [--poses N]
The rig is `service_capture.py`'s (real clock, 2 refreshes of latency, software-triggered
8-bit cameras, 4 ms exposure, 6 DN black level, replayed frames: one untimed pose renders
them first) with N cameras of the same size placed around the reference (the simulator's
default mounts), each pattern shown once for all of them. R is the capture time over the
vsync floor of the plan (as in service_capture.py: the one screen sets the pace, whatever
the number of cameras). S is from the last stored frame of any camera to the client
learning that the pose is ready, i.e. every camera's maps decoded (live, one worker task,
a thread per camera), fsynced and committed. Per pose: `lag` (the slowest camera's decode
catching up with its last frame), `finish` (the slowest camera's decoder finish and write),
and the CPU seconds of the server process (`api cpu`: HTTP, job, controller, frame stores)
and its workers (`wkr cpu`: every camera's decode).
Last line: `rig capture: N cameras, worst R x vsync floor; all maps ready S s after the
last frame`.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
from pathlib import Path

import httpx
from service_capture import (
    EXPOSURE_S,
    LATENCY_PERIODS,
    REFRESH_HZ,
    capture,
    cpu_seconds,
    start_server,
    vsync_floor,
)
from stall_probe import StallProbe, steal_ms


def rig_config(cameras: int, width: int, height: int) -> dict:
    """`cameras` simulated cameras of `width` x `height` on one 60 Hz screen."""
    camera = {"model": "mild_pinhole", "width": width, "height": height, "bit_depth": 8,
              "black_level_dn": 6, "replay": True, "max_frame_rate_hz": 240.0}
    return {"kind": "simulated", "clock": "real",
            "display": {"refresh_hz": REFRESH_HZ, "latency_periods": LATENCY_PERIODS},
            "cameras": [{"name": f"cam{k}", **camera} for k in range(cameras)],
            "settings": {"exposure_s": EXPOSURE_S, "pixel_format": "Mono8",
                         "trigger_mode": "software"}}


def bench(c: httpx.Client, pid: int, cameras: int, width: int, height: int, poses: int,
          probe: StallProbe) -> list[dict]:
    """Time `poses` poses after an untimed one that fills the replay caches."""
    rig = c.post("/rigs", json={"name": f"rig{cameras}",
                                "config": rig_config(cameras, width, height)})
    sess = c.post("/sessions", json={"rig_id": rig.raise_for_status().json()["id"],
                                     "preset": "default"}).json()
    capture(c, sess["id"])
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
        per = dec["cameras"].values()
        rows.append({"cameras": cameras, "size": f"{width}x{height}", "frames": n,
                     "floor_s": floor, "capture_s": cap["capture_s"],
                     "ratio": cap["capture_s"] / floor, "client_ratio": (last - posted) / floor,
                     "recaptures": cap["recaptures"], "late_ms": 1e3 * cap["trigger_late_s"],
                     "stall_ms": probe.worst_ms(posted, last),
                     "steal_ms": math.nan if steal0 is None else steal1 - steal0,
                     "lag_s": max(d["caught_up_at"] for d in per) - last,
                     "finish_s": max(d["finish_s"] + d["write_s"] for d in per),
                     "ready_s": seen - last, "api_cpu": api1 - api0,
                     "worker_cpu": workers1 - workers0, "load": load})
    return rows


COLUMNS = [  # header, row key, width, format
    ("cams", "cameras", 4, "d"), ("camera", "size", 10, "s"), ("frames", "frames", 6, "d"),
    ("floor s", "floor_s", 7, ".3f"), ("cap s", "capture_s", 6, ".2f"), ("R", "ratio", 5, ".2f"),
    ("R cl", "client_ratio", 5, ".2f"), ("recap", "recaptures", 5, "d"),
    ("late ms", "late_ms", 7, ".1f"), ("stall ms", "stall_ms", 8, ".1f"),
    ("steal ms", "steal_ms", 8, ".0f"), ("lag s", "lag_s", 6, ".2f"),
    ("finish", "finish_s", 6, ".2f"), ("S", "ready_s", 6, ".2f"),
    ("api cpu", "api_cpu", 7, ".2f"), ("wkr cpu", "worker_cpu", 7, ".2f"),
    ("load", "load", 5, ".1f")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--size", default="2448x2048")
    ap.add_argument("--poses", type=int, default=2)
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory(prefix="phasecal-bench-") as tmp:
        data = Path(tmp) / "data"
        proc, url = start_server(data)
        probe = StallProbe()
        try:
            with httpx.Client(base_url=url, timeout=600) as c:
                rows = bench(c, proc.pid, args.cameras, width, height, args.poses, probe)
        finally:
            probe.close()
            proc.terminate()
            proc.wait(30)
    print(f"rig capture benchmark: phasecal serve (worker processes), {args.cameras} simulated "
          f"cameras on one {REFRESH_HZ:g} Hz screen, replaying pre-rendered frames; load "
          f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    print(" ".join(f"{name:>{width}s}" for name, _, width, _ in COLUMNS))
    for r in rows:
        print(" ".join(f"{r[key]:>{width}{spec}}" for _, key, width, spec in COLUMNS))
    worst = max(max(r["ratio"], r["client_ratio"]) for r in rows)
    ready = max(r["ready_s"] for r in rows)
    print(f"rig capture: {args.cameras} cameras, worst {worst:.2f} x vsync floor; all maps ready "
          f"{ready:.2f} s after the last frame")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
