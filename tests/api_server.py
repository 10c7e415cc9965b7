"""Test helper: run `phasecal serve` as a real uvicorn subprocess on a free loopback port."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

from api.inprocess import free_port

ROOT = Path(__file__).resolve().parents[1]


class ServerProcess:
    """A `python -m api.cli serve` subprocess with its own data directory."""

    def __init__(self, data_dir: Path, *, rig: str = "simulated",
                 env: dict[str, str] | None = None) -> None:
        self.data_dir = data_dir
        self.rig = rig
        self.env = env or {}
        self.proc: subprocess.Popen | None = None
        self.url = ""
        self.log = data_dir.parent / f"{data_dir.name}-server.log"

    def start(self, timeout_s: float = 60.0) -> str:
        """Start and wait until /health answers; returns the base URL."""
        port = free_port()
        env = dict(os.environ, PHASECAL_DATA_DIR=str(self.data_dir), **self.env)
        env.pop("PHASECAL_DASK", None)
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "api.cli", "serve", "--port", str(port), "--rig", self.rig],
                cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
        self.url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited: {self.log.read_text()[-2000:]}")
            try:
                if httpx.get(f"{self.url}/health", timeout=1).status_code == 200:
                    return self.url
            except httpx.TransportError:
                time.sleep(0.1)
        raise RuntimeError(f"server did not answer in {timeout_s} s")

    def kill(self) -> None:
        """SIGKILL: the hard stop a power cut or OOM kill would be."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(30)

    def stop(self) -> None:
        """Graceful stop (SIGTERM), then kill if needed."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.kill()
