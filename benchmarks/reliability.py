"""Reliability of the REST service: bad inputs, kill -9 mid-fit, concurrent clients, and
the ordinary faults of a lab server: huge JSON bodies, slow preview clients, SIGTERM and
SIGINT, a full disk.

Drives `phasecal serve` subprocesses (default executor: worker processes) over HTTP and
prints what was tried, how many times, and the outcome: server errors (5xx), files
outside the data directory touched, orphaned processes after kill -9, finished poses lost
at restart, duplicate jobs from simultaneous requests; then one line per fault case (each
case's own table is in its module: reliability_bodies, _streams, _shutdown, _disk).
Fuzzing is `tests/api/test_api_schema.py`. The full-disk case mounts a tmpfs (root).

    .venv/bin/python benchmarks/reliability.py [--kills 3] [--concurrent 10] [--quick]
"""

from __future__ import annotations

import argparse
import hashlib
import io
import os
import signal
import sys
import tempfile
import threading
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
from benchmarks.reliability_bodies import run_body_cases  # noqa: E402
from benchmarks.reliability_disk import run_disk_case  # noqa: E402
from benchmarks.reliability_shutdown import run_shutdown_cases  # noqa: E402
from benchmarks.reliability_streams import run_stream_cases  # noqa: E402
from benchmarks.serve_process import descendants, running, start_serve  # noqa: E402
from calibration.shared.plan import ScreenGeometry  # noqa: E402
from hw_mocks.cameras import mild_pinhole  # noqa: E402
from hw_mocks.poses import random_poses  # noqa: E402
from hw_mocks.synthetic import synthetic_maps  # noqa: E402

PLAN = build_plan(640, 480, 0.5, preset="fast")
MAX_UPLOAD = 16 << 20


class Tolerant(httpx.Client):
    """A client that reports a dropped connection as HTTP 599 (a server failure) instead of
    raising, so one bad answer does not end the run."""

    def request(self, *args, **kwargs) -> httpx.Response:
        try:
            return super().request(*args, **kwargs)
        except (httpx.RemoteProtocolError, httpx.ReadError):
            return httpx.Response(599, headers={"content-type": "text/plain"})


class Server:
    """`python -m api.cli serve` on a free port with its own data directory."""

    def __init__(self, data: Path) -> None:
        self.data, self.proc, self.url = data, None, ""

    def start(self) -> Tolerant:
        self.proc, self.url = start_serve(
            self.data, env={"PHASECAL_MAX_UPLOAD_BYTES": str(MAX_UPLOAD)})
        return Tolerant(base_url=self.url, timeout=120)

    def children(self) -> set[int]:
        return descendants(self.proc.pid)


def maps_bytes(seed: int, size: tuple[int, int] = (160, 120), **override) -> bytes:
    cam = mild_pinhole(*size)
    rng = np.random.default_rng(seed)
    maps, _ = synthetic_maps(cam, random_poses(cam, PLAN.screen, 1, rng)[0], PLAN.screen,
                             sigma_px=0.05, rng=rng)
    maps.meta["plan_digest"] = PLAN.digest()
    arrays = dict(np.load(io.BytesIO(maps.to_npz_bytes())))
    arrays.update(override)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def bad_requests(c: httpx.Client, sid: str, cal: str, outside: Path, data: Path) -> list:
    """(label, response) for every bad input tried."""
    hw = {"kind": "hardware", "screen": {"pitch_mm": 0.25}}
    sdl = {"backend": "sdl", "video_driver": "dummy", "width": 64, "height": 48}
    os.symlink(outside / "clip.mkv", data / "link.mkv")
    rigs = [{**hw, "display": {"backend": "framebuffer", "device": str(outside / "victim.bin"),
                               "width": 16, "height": 16}, "camera": {"backend": "opencv"}},
            {**hw, "display": {"backend": "framebuffer", "device": "/dev/fb0", "width": 16,
                               "height": 16, "sysfs_root": str(outside)},
             "camera": {"backend": "opencv"}}]
    rigs += [{**hw, "display": sdl, "camera": {"backend": "opencv", "source": s}}
             for s in (str(outside / "clip.mkv"), "../clip.mkv", "link.mkv", "http://x/y.mkv",
                       "/dev/sda", 7)]
    rigs += [{**hw, "display": sdl, "camera": {"backend": "aravis", "device": "10.0.0.1"}}]
    rigs += [{"screen": {"pitch_mm": p}} for p in (0, [0.25, 0], -1)]
    out = [(f"rig {i}", c.post("/rigs", json={"name": f"bad{i}", "config": r}))
           for i, r in enumerate(rigs)]
    nan_like = np.full((120, 160), np.nan)
    maps = {"0x0": {k: np.zeros((0, 0)) for k in ("x", "y")},
            "all-NaN": {"x": nan_like, "mask": np.ones((120, 160), bool)},
            "sigma<0": {"sigma_x": np.full((120, 160), -1, np.float32)},
            "sigma inf": {"sigma_y": np.full((120, 160), np.inf, np.float32)},
            "1e300": {"y": np.full((120, 160), 1e300)}}
    for label, override in maps.items():
        out.append((f"maps {label}", c.post(f"/sessions/{sid}/poses/import-maps",
                                            files={"file": ("m.npz",
                                                            maps_bytes(1, **override))})))
    big = 1500
    bomb = io.BytesIO()
    np.savez_compressed(bomb, **{k: np.zeros((big, big)) for k in ("x", "y", "sigma_x",
                                                                   "sigma_y", "mask")},
                        modulation_x=np.zeros(1), modulation_y=np.zeros(1), meta=np.array("{}"))
    out.append(("maps zip bomb", c.post(f"/sessions/{sid}/poses/import-maps",
                                        files={"file": ("bomb.npz", bomb.getvalue())})))
    png = cv2.imencode(".png", np.full((120, 160), 90, np.uint8))[1].tobytes()
    png16 = cv2.imencode(".png", np.full((120, 160), 90, np.uint16))[1].tobytes()
    for label, bad in (("0-byte PNG", b""), ("16-bit among 8-bit", png16), ("garbage", b"x")):
        files = [("files", (f"frame_{i:04d}.png", bad if i == 3 else png, "image/png"))
                 for i in range(len(PLAN.frames))]
        out.append((f"frames {label}", c.post(f"/sessions/{sid}/poses/import", files=files)))
    for path in ("/sessions", "/jobs", "/calibrations"):
        out.append((f"offset {path}", c.get(path, params={"offset": 2**63})))
    rig = c.get("/rigs").json()[0]["id"]
    js = {"content-type": "application/json"}
    for body in ('{"rvec": [NaN, 0, 0], "tvec_mm": [0, 0, 300]}',
                 '{"rvec": [false, 0, 0], "tvec_mm": [0, 0, 300]}',
                 '{"rvec": [0, 0, 0], "tvec_mm": [0, 0, Infinity]}'):
        out.append(("screen pose " + body[:24], c.put(f"/rigs/{rig}/screen-pose", content=body,
                                                      headers=js)))
    out.append(("points false", c.post(f"{cal}/project", json={"points": [[False, 0, 1]]})))
    out.append(("pixels string", c.post(f"{cal}/unproject", json={"pixels": [["1", 2]]})))
    out.append(("exposure true", c.put(f"/rigs/{rig}/camera/settings",
                                       json={"exposure_s": True})))
    return out


def fingerprint(folder: Path) -> dict[str, tuple[str, float]]:
    return {str(p): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime)
            for p in folder.rglob("*") if p.is_file() and not p.is_symlink()}


def session_with_poses(c: httpx.Client, n: int = 3) -> tuple[str, list[str]]:
    sid = c.post("/sessions", json={"plan": PLAN.to_dict()}).json()["id"]
    poses = [c.post(f"/sessions/{sid}/poses/import-maps",
                    files={"file": ("m.npz", maps_bytes(10 + k))}).json()["id"] for k in range(n)]
    return sid, poses


def wait_job(c: httpx.Client, job: dict, until) -> dict:
    deadline = time.monotonic() + 300
    while not until(job) and time.monotonic() < deadline:
        time.sleep(0.05)
        job = c.get(f"/jobs/{job['id']}").json()
    return job


def kill_rounds(srv: Server, c: httpx.Client, sid: str, rounds: int) -> dict[str, int]:
    stats = {"kills": 0, "orphans": 0, "outputs committed by orphans": 0,
             "finished poses lost": 0, "stale staging left": 0}
    for _ in range(rounds):
        ready = [p["id"] for p in c.get(f"/sessions/{sid}/poses").json() if p["status"] == "ready"]
        job = c.post(f"/sessions/{sid}/calibrations", json={"model": "sgcc"}).json()
        wait_job(c, job, lambda j: j["stage"] not in ("queued", "starting", "load")
                 or j["status"] not in ("queued", "running"))
        kids = srv.children()
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(30)
        stats["kills"] += 1
        deadline = time.monotonic() + 10
        while running(kids) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = running(kids)
        stats["orphans"] += len(left)
        for p in left:
            os.kill(p, signal.SIGKILL)
        time.sleep(1.0)
        cal_dir = srv.data / "calibrations" / job["resource"].rsplit("/", 1)[-1]
        stats["outputs committed by orphans"] += int((cal_dir / "model.json").exists())
        c.close()
        c = srv.start()
        stats["stale staging left"] += len(list((srv.data / "tmp").iterdir()))
        for pid in ready:
            r = c.get(f"/sessions/{sid}/poses/{pid}/maps.npz")
            stats["finished poses lost"] += int(r.status_code != 200)
    c.close()
    return stats


def concurrent_resumes(c: httpx.Client, n: int) -> tuple[int, int]:
    """n simultaneous resumes of one cancelled capture: (202 answers, capture jobs started)."""
    screen = ScreenGeometry(320, 240, (0.5, 0.5))
    cfg = demo_rig_config(320, 240, camera="mild_pinhole", screen=screen)
    cfg["camera"]["supersample"] = 4
    rig = c.post("/rigs", json={"name": "slow", "config": cfg}).json()
    sess = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()
    pose = {"rvec": [0.0, 0.0, 0.0], "tvec_mm": [-80.0, -60.0, 250.0]}
    job = c.post(f"/sessions/{sess['id']}/poses", json={"screen_pose": pose}).json()
    wait_job(c, job, lambda j: j["done"] >= 3 or j["status"] not in ("queued", "running"))
    c.post(f"/jobs/{job['id']}/cancel")
    job = wait_job(c, job, lambda j: j["status"] not in ("queued", "running"))
    barrier, codes = threading.Barrier(n), []

    def resume() -> None:
        with httpx.Client(base_url=c.base_url, timeout=120) as own:
            barrier.wait()
            codes.append(own.post(f"{job['resource']}/resume").status_code)

    threads = [threading.Thread(target=resume) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    jobs = c.get("/jobs", params={"kind": "capture", "limit": 500}).json()["items"]
    started = [j for j in jobs if j["resource"] == job["resource"] and j["id"] != job["id"]]
    for j in started:
        c.post(f"/jobs/{j['id']}/cancel")
    return codes.count(202), len(started)


def held(cases: list[dict[str, Any]]) -> str:
    """How many of a fault's cases held (None: not run, e.g. without root)."""
    ran = [c for c in cases if c.get("held") is not None]
    skipped = f", {len(cases) - len(ran)} not run" if len(ran) < len(cases) else ""
    return f"{sum(bool(c['held']) for c in ran)} of {len(ran)} held{skipped}"


def fault_rows(srv: Server, quick: bool) -> list[tuple[str, int, str]]:
    """The ordinary faults, one line each: huge JSON bodies and slow preview clients on the
    running server, SIGTERM/SIGINT and a full disk on servers of their own."""
    rows = []
    bodies = run_body_cases(srv.url, srv.proc.pid)
    rows.append(("50 MB / near-limit JSON bodies of every shape", len(bodies), held(bodies)))
    streams = run_stream_cases(srv.url, clients=50 if quick else 200)
    worst = max(r["p99_ms"] for r in streams)
    rows.append((f"{streams[0]['clients']} preview clients hang up, 8 fps values",
                 len(streams), f"{held(streams)}; worst p99 of other routes {worst:.0f} ms"))
    stops = run_shutdown_cases()
    rows.append(("SIGTERM / SIGINT mid-capture (server, group)", len(stops),
                 f"{held(stops)}; exit codes {sorted({r['exit code'] for r in stops})}"))
    disk = run_disk_case()
    rows.append(("capture until a tmpfs is full, DELETE, resume", len(disk),
                 f"{held(disk)}; {disk[0]['outcome']}"))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=3)
    ap.add_argument("--concurrent", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="50 preview clients instead of 200")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="phasecal-reliability-") as tmp:
        outside = Path(tmp) / "outside"
        outside.mkdir()
        (outside / "victim.bin").write_bytes(os.urandom(1 << 16))
        (outside / "clip.mkv").write_bytes(os.urandom(1 << 10))
        before = fingerprint(outside)
        srv = Server(Path(tmp) / "data")
        c = srv.start()
        try:
            sid, _ = session_with_poses(c)
            job = c.post(f"/sessions/{sid}/calibrations", json={"model": "sgcc"}).json()
            job = wait_job(c, job, lambda j: j["status"] not in ("queued", "running"))
            cal = job["resource"]
            answers = bad_requests(c, sid, cal, outside, srv.data)
            errors = [(k, r.status_code) for k, r in answers if r.status_code >= 500]
            not_problem = [k for k, r in answers if r.status_code < 400
                           or "problem+json" not in r.headers.get("content-type", "")]
            rows.append(("bad inputs (rigs, maps, frames, offsets, numbers)", len(answers),
                         f"{len(errors)} server errors, {len(not_problem)} not a 4xx problem"
                         + (f" {not_problem}" if not_problem else "")))
            centre = c.post(f"{cal}/project", json={"points": [[0, 0, 0]]})
            rows.append(("project (0,0,0) on sGCC", 1,
                         f"HTTP {centre.status_code}, pixels {centre.json().get('pixels')}"))
            ok, started = concurrent_resumes(c, args.concurrent)
            rows.append((f"{args.concurrent} simultaneous resumes of one pose", args.concurrent,
                         f"{ok} accepted, {started} capture job(s) started"))
            after = fingerprint(outside)
            touched = sum(before.get(k) != v for k, v in after.items()) + len(
                set(after) ^ set(before))
            rows.append(("files outside the data directory touched", len(before),
                         f"{touched} touched"))
            rows += fault_rows(srv, args.quick)
            stats = kill_rounds(srv, c, sid, args.kills)
            rows.append(("kill -9 of serve during an sGCC fit", stats["kills"],
                         ", ".join(f"{v} {k}" for k, v in stats.items() if k != "kills")))
        finally:
            kids = srv.children() if srv.proc and srv.proc.poll() is None else set()
            if srv.proc and srv.proc.poll() is None:
                srv.proc.terminate()
                srv.proc.wait(60)
            time.sleep(2)
            rows.append(("graceful stop", 1, f"{len(running(kids))} processes left"))
    print(f"\nreliability (cpus {os.cpu_count()}, load {os.getloadavg()[0]:.1f})")
    print(f"{'what was tried':<46} {'n':>4}  outcome")
    for what, n, outcome in rows:
        print(f"{what:<46} {n:>4}  {outcome}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
