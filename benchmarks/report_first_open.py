"""First open of a calibration report over HTTP, on `phasecal serve` (worker processes) with
a simulated rig: how long the first GET of report.html takes once the calibration job said
succeeded (the job draws the report), against what drawing it on that first request costs
(the report folder removed: the GET answers 202 at once and the report is drawn in the
background; the time until it answers 200 is what a first GET that drew the page itself
used to block for). CPU seconds of the server's process tree are counted beside each.

    nice .venv/bin/python benchmarks/report_first_open.py [--poses 5] [--size 320x240]
        [--save DIR]   # also save the self-contained report and a diff page there
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from acquisition.patterns import build_plan  # noqa: E402
from api.demo import demo_rig_config  # noqa: E402
from benchmarks.serve_process import descendants, start_serve  # noqa: E402
from hw_mocks.cameras import mild_pinhole  # noqa: E402
from hw_mocks.poses import random_poses  # noqa: E402

TICKS = os.sysconf("SC_CLK_TCK")


def tree_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process and every live process below it."""
    total = 0
    for p in {pid} | descendants(pid):
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])
    return total / TICKS


def wait_job(http: httpx.Client, job: dict[str, Any]) -> dict[str, Any]:
    """Poll a job until it ends."""
    while job["status"] not in ("succeeded", "failed", "cancelled"):
        time.sleep(0.05)
        job = http.get(f"/jobs/{job['id']}").json()
    if job["status"] != "succeeded":
        raise RuntimeError(f"job {job['id']} {job['status']}: {job.get('error')}")
    return job


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=5)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--save", type=Path, default=None)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    screen = build_plan(w, h, 0.5, preset="fast").screen
    data = Path(tempfile.mkdtemp(prefix="phasecal-report-bench-"))
    proc, url = start_serve(data / "data")
    try:
        with httpx.Client(base_url=url, timeout=600) as http:
            rig = http.post("/rigs", json={"name": "bench", "config": demo_rig_config(
                w, h, camera="mild_pinhole", screen=screen)}).json()
            ses = http.post("/sessions", json={"name": "bench", "rig_id": rig["id"],
                                               "preset": "fast"}).json()
            poses = []
            for p in random_poses(mild_pinhole(w, h), screen, args.poses,
                                  np.random.default_rng(5)):
                rvec = cv2.Rodrigues(np.asarray(p.rotation, np.float64))[0].ravel().tolist()
                job = wait_job(http, http.post(f"/sessions/{ses['id']}/poses", json={
                    "screen_pose": {"rvec": rvec, "tvec_mm": list(map(float, p.translation))}}
                                               ).json())
                poses.append(job["resource"].rsplit("/", 1)[-1])
            cals = []
            for model in ("opencv5", "opencv-rational"):
                cpu0, t0 = tree_cpu_s(proc.pid), time.perf_counter()
                job = wait_job(http, http.post(f"/sessions/{ses['id']}/calibrations", json={
                    "model": model, "pose_ids": poses[:-1], "heldout_pose_ids": poses[-1:]}
                                               ).json())
                print(f"calibrate {model} (fit + report): wall {time.perf_counter() - t0:.2f} s,"
                      f" cpu {tree_cpu_s(proc.pid) - cpu0:.2f} s")
                cals.append(job["resource"].rsplit("/", 1)[-1])
            cal = cals[0]
            cpu0, t0 = tree_cpu_s(proc.pid), time.perf_counter()
            r = http.get(f"/calibrations/{cal}/report.html")
            print(f"after: first GET right after the job: {r.status_code}, "
                  f"{(time.perf_counter() - t0) * 1e3:.1f} ms, {len(r.content)} bytes, cpu "
                  f"{tree_cpu_s(proc.pid) - cpu0:.2f} s")
            shutil.rmtree(data / "data" / "calibrations" / cal / "report")
            cpu0, t0 = tree_cpu_s(proc.pid), time.perf_counter()
            r = http.get(f"/calibrations/{cal}/report.html")
            first = time.perf_counter() - t0
            while r.status_code == 202:
                time.sleep(0.05)
                r = http.get(f"/calibrations/{cal}/report.html")
            print(f"drawn on request: first answer {first * 1e3:.1f} ms (202, reloads itself); "
                  f"report after {time.perf_counter() - t0:.2f} s, cpu "
                  f"{tree_cpu_s(proc.pid) - cpu0:.2f} s (what a first GET drawing the page "
                  "blocked for)")
            if args.save:
                args.save.mkdir(parents=True, exist_ok=True)
                (args.save / "report.html").write_bytes(http.get(
                    f"/calibrations/{cal}/report.html", params={"download": 1}).content)
                diff = http.get(f"/calibrations/{cals[0]}/diff/{cals[1]}").json()
                for name in ("diff.html", "diff.png", "diff_sigma.png"):
                    (args.save / name).write_bytes(http.get(
                        f"/calibrations/{cals[0]}/diff/{cals[1]}/{name}").content)
                print(f"diff: {diff['verdict']}")
    finally:
        proc.terminate()
        proc.wait(60)
        shutil.rmtree(data, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
