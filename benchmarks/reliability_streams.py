"""MJPEG clients that take one frame and hang up: do the other routes keep answering?

For every `fps` a client may ask for (the allowed extremes and disallowed values), CLIENTS
clients (in a process of their own) open `/rigs/default/camera/preview?fps=F` at once,
read up to the end of the first JPEG (or the refusal: 422 for a disallowed fps, 429 beyond
the stream caps) and hang up. Meanwhile a prober thread times GET /sessions (a sync route:
it needs a thread of the server's pool) and GET /health (async) back to back on one
keep-alive connection, until 1.5 s after the last client left, when a stream that still
held a thread would show.
A row: clients, fps, status codes seen, probes, p99 and max probe latency in ms, held
(p99 under 100 ms, no probe failed, and only 200/422/429 answers: 422 exactly for the
disallowed fps).

    .venv/bin/python benchmarks/reliability_streams.py [--clients 200]

starts `python -m api.cli serve` (simulated rig) on a free port with a temporary data
directory; `run_stream_cases(base_url)` runs against a server already started.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from api.routes.preview import MAX_FPS, MIN_FPS  # noqa: E402
from benchmarks.serve_process import start_serve  # noqa: E402

CLIENTS = 200
#: allowed: the bounds and a middle value; disallowed: below, far below, zero, above
FPS_CASES: tuple[float, ...] = (MIN_FPS, 1.0, MAX_FPS, 0.05, 1e-6, 0.0, 30.0, 1e6)
P99_LIMIT_MS = 100.0
LINGER_S = 1.5  # probing goes on this long after the last client hung up
PROBE_PATHS = ("/sessions", "/health")


class Prober(threading.Thread):
    """Times PROBE_PATHS in turn on one keep-alive connection until `stop` is set."""

    def __init__(self, base_url: str) -> None:
        super().__init__(name="prober", daemon=True)
        self.base_url = base_url
        self.ready, self.stop = threading.Event(), threading.Event()
        self.samples: list[tuple[float, float]] = []  # (monotonic start, ms)
        self.errors: Counter[str] = Counter()

    def run(self) -> None:
        with httpx.Client(base_url=self.base_url, timeout=60) as c:
            c.get("/health")  # connect before the crowd comes
            self.ready.set()
            i = 0
            while not self.stop.is_set():
                path = PROBE_PATHS[i % len(PROBE_PATHS)]
                i += 1
                t0 = time.perf_counter()
                try:
                    r = c.get(path)
                except httpx.HTTPError as exc:
                    self.errors[f"{path} {type(exc).__name__}"] += 1
                    continue
                if r.status_code != 200:
                    self.errors[f"{path} {r.status_code}"] += 1
                self.samples.append((t0, (time.perf_counter() - t0) * 1e3))
                time.sleep(0.005)


async def one_client(host: str, port: int, path: str, timeout_s: float = 60) -> str:
    """Open the stream, read the first frame (or the refusal), hang up; the status seen."""
    try:
        reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port), timeout_s)
    except (OSError, TimeoutError) as exc:
        return f"connect {type(exc).__name__}"
    try:
        writer.write(f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\n\r\n".encode())
        head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), timeout_s)
        status = head.split(b" ", 2)[1].decode()
        if status == "200":
            await asyncio.wait_for(reader.readuntil(b"\xff\xd9"), timeout_s)  # end of JPEG
        return status
    except (OSError, TimeoutError, asyncio.IncompleteReadError,
            asyncio.LimitOverrunError) as exc:
        return type(exc).__name__
    finally:
        writer.close()  # the hang-up


async def crowd(base_url: str, fps: float, clients: int) -> Counter[str]:
    """CLIENTS preview clients at once; how many saw each status."""
    parts = urlsplit(base_url)
    path = f"/rigs/default/camera/preview?fps={fps:g}"
    seen = await asyncio.gather(*(one_client(parts.hostname or "127.0.0.1",
                                             parts.port or 80, path) for _ in range(clients)))
    return Counter(seen)


def run_crowd(base_url: str, fps: float, clients: int) -> tuple[Counter[str], float, float]:
    """The crowd in its own process (so that the prober's timing is not its CPU); the
    statuses seen and when the crowd started and ended (`time.perf_counter`, which is
    CLOCK_MONOTONIC on Linux: the same clock in both processes)."""
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--crowd", base_url,
                           repr(fps), str(clients)], capture_output=True, text=True,
                          timeout=600, check=True)
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    return Counter(got["statuses"]), float(got["start"]), float(got["end"])


def run_case(base_url: str, fps: float, clients: int = CLIENTS) -> dict[str, Any]:
    """One fps: the crowd against the prober; the row."""
    prober = Prober(base_url)
    prober.start()
    if not prober.ready.wait(120):
        raise RuntimeError("the prober could not reach the server")
    statuses, start, end = run_crowd(base_url, fps, clients)
    time.sleep(LINGER_S)
    prober.stop.set()
    prober.join(120)
    # the probes that overlapped the crowd or the time after it
    times = [ms for t0, ms in prober.samples if t0 + ms / 1e3 >= start and t0 <= end + LINGER_S]
    errors = dict(prober.errors)
    allowed = MIN_FPS <= fps <= MAX_FPS
    p99 = float(np.percentile(times, 99)) if times else math.inf
    expected = {"200", "429"} if allowed else {"422"}
    held = (p99 < P99_LIMIT_MS and not errors and set(statuses) <= expected
            and (not allowed or statuses["200"] > 0))
    return {"clients": clients, "fps": fps, "allowed": allowed,
            "statuses": dict(sorted(statuses.items())), "crowd_s": round(end - start, 2),
            "probes": len(times), "probe_errors": errors, "p99_ms": round(p99, 1),
            "max_ms": round(max(times, default=math.inf), 1), "held": held}


def quiet_p99_ms(base_url: str, seconds: float = 2.0) -> float:
    """p99 of the same probes with no crowd: this machine's noise floor."""
    prober = Prober(base_url)
    prober.start()
    if not prober.ready.wait(120):
        raise RuntimeError("the prober could not reach the server")
    time.sleep(seconds)
    prober.stop.set()
    prober.join(120)
    return float(np.percentile([ms for _, ms in prober.samples], 99))


def run_stream_cases(base_url: str, clients: int = CLIENTS,
                     fps_cases: Sequence[float] = FPS_CASES) -> list[dict[str, Any]]:
    """One row per fps asked (see the module docstring) against the server at `base_url`."""
    return [run_case(base_url, fps, clients) for fps in fps_cases]


def print_table(rows: list[dict[str, Any]]) -> None:
    print(f"{'fps':>8} {'clients':>7} {'statuses':<28} {'probes':>6} {'p99 ms':>7} "
          f"{'max ms':>7} {'crowd s':>7}  held")
    for r in rows:
        codes = " ".join(f"{k}x{v}" for k, v in r["statuses"].items())
        errs = f"  probe errors {r['probe_errors']}" if r["probe_errors"] else ""
        print(f"{r['fps']:>8g} {r['clients']:>7} {codes:<28} {r['probes']:>6} "
              f"{r['p99_ms']:>7.1f} {r['max_ms']:>7.1f} {r['crowd_s']:>7.2f}  "
              f"{'yes' if r['held'] else 'NO'}{errs}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clients", type=int, default=CLIENTS)
    ap.add_argument("--crowd", nargs=3, metavar=("URL", "FPS", "CLIENTS"),
                    help="(internal) run one crowd and print its statuses as JSON")
    args = ap.parse_args()
    if args.crowd:
        url, fps, clients = args.crowd[0], float(args.crowd[1]), int(args.crowd[2])
        start = time.perf_counter()
        seen = asyncio.run(crowd(url, fps, clients))
        print(json.dumps({"statuses": seen, "start": start, "end": time.perf_counter()}))
        return 0
    with tempfile.TemporaryDirectory(prefix="phasecal-streams-") as tmp:
        proc, url = start_serve(Path(tmp) / "data", log=Path(tmp) / "server.log")
        try:
            quiet = quiet_p99_ms(url)
            rows = run_stream_cases(url, args.clients)
        finally:
            proc.terminate()
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
    print(f"probes with no crowd: p99 {quiet:.1f} ms")
    print_table(rows)
    return 0 if all(r["held"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
