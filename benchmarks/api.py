"""REST latency under load: 50 concurrent clients poll a job's status while a calibration runs.

Starts `phasecal serve` as a subprocess on a free loopback port (its default executor,
worker processes, unless --executor says otherwise),
imports synthetic decoded maps (hw_mocks ground truth) as poses, starts a calibration and
measures GET /jobs/<id> latency from N concurrent clients until it ends; an idle run of
the same polling gives the baseline. Prints p50/p99/max latency as the clients see it and
as the server measured it (its `Server-Timing` header). Goal: p99 < 50 ms server-side.

    .venv/bin/python benchmarks/api.py [--clients 50] [--model sgcc] [--poses 4]
                                       [--client raw|httpx] [--interval 0.1]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from api.inprocess import free_port  # noqa: E402


def start_server(data_dir: Path, executor: str) -> tuple[subprocess.Popen, str]:
    """`python -m api.cli serve` on a free port; returns (process, base URL) once healthy."""
    port = free_port()
    env = dict(os.environ, PHASECAL_DATA_DIR=str(data_dir))
    env.pop("PHASECAL_DASK", None)
    proc = subprocess.Popen([sys.executable, "-m", "api.cli", "serve", "--port", str(port),
                             "--executor", executor],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{url}/health", timeout=1).status_code == 200:
                return proc, url
        except httpx.TransportError:
            time.sleep(0.1)
    proc.kill()
    err = proc.stderr.read().decode() if proc.stderr else ""
    raise RuntimeError(f"server did not start: {err}")


def prepare(url: str, n_poses: int, width: int, height: int) -> str:
    """A session whose poses are synthetic maps of a wide-angle camera; returns its id."""
    from acquisition.patterns import build_plan
    from hw_mocks.cameras import wide_fisheye
    from hw_mocks.poses import random_poses
    from hw_mocks.synthetic import synthetic_maps

    plan = build_plan(1920, 1080, 0.2745, preset="fast")
    with httpx.Client(base_url=url, timeout=60) as c:
        sess = c.post("/sessions", json={"name": "bench", "plan": plan.to_dict()}).json()
        cam = wide_fisheye(width, height)
        rng = np.random.default_rng(3)
        for k, pose in enumerate(random_poses(cam, plan.screen, n_poses, rng)):
            maps, _ = synthetic_maps(cam, pose, plan.screen, sigma_px=0.05, rng=rng,
                                     pose_id=f"bench{k}")
            maps.meta["plan_digest"] = plan.digest()
            r = c.post(f"/sessions/{sess['id']}/poses/import-maps",
                       files={"file": ("maps.npz", maps.to_npz_bytes())})
            r.raise_for_status()
    return sess["id"]


async def _get(reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
               request: bytes) -> tuple[int, float]:
    """One keep-alive HTTP/1.1 GET on an open connection; (status, server-side seconds).

    The server's own time comes from its `Server-Timing: app;dur=<ms>` header.
    """
    writer.write(request)
    await writer.drain()
    status_line = await reader.readline()
    length, server_s = 0, float("nan")
    while (line := await reader.readline()) not in (b"\r\n", b""):
        name, _, value = line.partition(b":")
        key = name.strip().lower()
        if key == b"content-length":
            length = int(value)
        elif key == b"server-timing" and b"dur=" in value:
            server_s = float(value.split(b"dur=")[1].split(b";")[0]) / 1e3
    await reader.readexactly(length)
    return int(status_line.split()[1]), server_s


async def _get_retrying(c: httpx.AsyncClient, path: str) -> httpx.Response:
    """GET once more when a kept-alive connection was closed by the server as the request
    went out (uvicorn drops connections idle for 5 s; a starved client loop can idle that
    long between its own polls)."""
    try:
        return await c.get(path)
    except httpx.RemoteProtocolError:
        return await c.get(path)


def _server_s(response: httpx.Response) -> float:
    value = response.headers.get("server-timing", "")
    return float(value.split("dur=")[1].split(";")[0]) / 1e3 if "dur=" in value else float("nan")


async def poll(url: str, path: str, clients: int, stop: asyncio.Event,
               min_requests: int = 0, interval_s: float = 0.0,
               client: str = "raw") -> list[tuple[float, float]]:
    """(client-observed, server-side) seconds of GET `path` from `clients` pollers.

    `raw`: a minimal keep-alive socket client, so the load generator's own CPU use (it
    shares the cores with the server) stays small. `httpx`: one httpx.AsyncClient per
    poller, as a typical probe script would poll.
    """
    host, port = url.removeprefix("http://").split(":")
    request = f"GET {path} HTTP/1.1\r\nHost: {host}\r\n\r\n".encode()
    lat: list[tuple[float, float]] = []

    async def loop(get) -> None:
        n = 0
        while not stop.is_set() or n < min_requests:
            t0 = time.perf_counter()
            status, server_s = await get()
            lat.append((time.perf_counter() - t0, server_s))
            if status != 200:
                raise RuntimeError(f"GET {path}: HTTP {status}")
            n += 1
            if interval_s:
                await asyncio.sleep(interval_s)

    async def one() -> None:
        if client == "httpx":
            async with httpx.AsyncClient(base_url=url, timeout=60) as c:
                async def get() -> tuple[int, float]:
                    r = await _get_retrying(c, path)
                    return r.status_code, _server_s(r)
                await loop(get)
            return
        reader, writer = await asyncio.open_connection(host, int(port))
        try:
            await loop(lambda: _get(reader, writer, request))
        finally:
            writer.close()

    await asyncio.gather(*(one() for _ in range(clients)))
    return lat


async def measure(url: str, session_id: str, clients: int, model: str,
                  interval_s: float, client: str) -> dict[str, list[tuple[float, float]]]:
    """Idle baseline, then polling while a calibration job runs."""
    async with httpx.AsyncClient(base_url=url, timeout=60) as c:
        stop = asyncio.Event()
        stop.set()
        idle = await poll(url, "/health", clients, stop, min_requests=20, interval_s=interval_s,
                          client=client)
        job = (await c.post(f"/sessions/{session_id}/calibrations", json={"model": model})).json()
        stop = asyncio.Event()
        task = asyncio.create_task(poll(url, f"/jobs/{job['id']}", clients, stop,
                                        interval_s=interval_s, client=client))
        t0 = time.perf_counter()
        while True:
            state = (await _get_retrying(c, f"/jobs/{job['id']}")).json()
            if state["status"] not in ("queued", "running"):
                break
            await asyncio.sleep(0.2)
        stop.set()
        busy = await task
        print(f"calibration {model}: {state['status']} in {time.perf_counter() - t0:.1f} s"
              + (f" ({state['error']})" if state["error"] else ""))
    return {"idle": idle, f"during {model}": busy}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--model", default="sgcc")
    ap.add_argument("--poses", type=int, default=4)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--interval", type=float, default=0.1,
                    help="pause between one client's polls, s (0: back-to-back saturation)")
    ap.add_argument("--executor", default="processes",
                    help="processes (serve's default), threads or tcp://...")
    ap.add_argument("--client", choices=("raw", "httpx"), default="raw",
                    help="raw keep-alive sockets (light) or one httpx.AsyncClient per poller")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="phasecal-bench-") as tmp:
        proc, url = start_server(Path(tmp), args.executor)
        try:
            sid = prepare(url, args.poses, args.width, args.height)
            results = asyncio.run(measure(url, sid, args.clients, args.model, args.interval,
                                          args.client))
        finally:
            proc.terminate()
            proc.wait(30)
    print(f"\n{args.clients} {args.client} clients polling GET /jobs/<id> every {args.interval} s, "
          f"executor {args.executor} (cpus: {os.cpu_count()}, load {os.getloadavg()[0]:.1f})")
    print(f"{'':<16} {'':>9} {'client-observed ms':^26} {'server-side ms':^26}")
    print(f"{'scenario':<16} {'requests':>9} " + f"{'p50':>8} {'p99':>8} {'max':>8} " * 2)
    for name, lat in results.items():
        ms = np.asarray(lat) * 1e3
        cells = [f"{np.percentile(col, 50):8.2f} {np.percentile(col, 99):8.2f} "
                 f"{np.max(col):8.2f}" for col in (ms[:, 0], ms[:, 1])]
        print(f"{name:<16} {len(ms):9d} {cells[0]} {cells[1]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
