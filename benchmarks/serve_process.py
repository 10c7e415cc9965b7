"""`phasecal serve` as a subprocess on a free loopback port, for the benchmarks that drive
the real service over HTTP (reliability and its fault cases)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from api.inprocess import free_port  # noqa: E402


def start_serve(data_dir: Path, *, log: Path | None = None, env: dict[str, str] | None = None,
                executor: str | None = None, new_session: bool = False,
                timeout_s: float = 120.0) -> tuple[subprocess.Popen, str]:
    """Start `python -m api.cli serve` (simulated rig) with its own data directory and wait
    until /health answers; (process, base URL). `new_session`: the server leads a process
    group of its own (signals can be sent to the group, as systemd or a terminal does)."""
    port = free_port()
    proc_env = {k: v for k, v in os.environ.items()
                if k not in ("PHASECAL_DASK", "PHASECAL_DATA_DIR")}
    proc_env.update(env or {})
    args = [sys.executable, "-m", "api.cli", "serve", "--port", str(port), "--data-dir",
            str(data_dir)] + (["--executor", executor] if executor else [])
    with open(log or os.devnull, "ab") as out:
        proc = subprocess.Popen(args, cwd=ROOT, env=proc_env, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=new_session)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if httpx.get(f"{url}/health", timeout=2).status_code == 200:
                return proc, url
        except httpx.TransportError:
            time.sleep(0.1)
    if proc.poll() is None:
        if new_session:
            os.killpg(proc.pid, signal.SIGKILL)
        else:
            proc.kill()
        proc.wait(30)
    tail = log.read_text()[-2000:] if log is not None and log.is_file() else ""
    raise RuntimeError(f"phasecal serve did not start (exit {proc.returncode}) {tail}")


def descendants(pid: int) -> set[int]:
    """Every live process below `pid` (from /proc/<pid>/task/*/children)."""
    found: set[int] = set()
    todo = [pid]
    while todo:
        for task in Path(f"/proc/{todo.pop()}/task").glob("*"):
            try:
                kids = {int(k) for k in (task / "children").read_text().split()}
            except OSError:
                continue
            todo += list(kids - found)
            found |= kids
    return found


def running(pids: set[int]) -> set[int]:
    """The pids that still run (zombies count as gone)."""
    out = set()
    for p in pids:
        try:
            if Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
                out.add(p)
        except OSError:
            pass
    return out
