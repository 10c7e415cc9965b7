"""kill -9 of `phasecal serve` mid-fit: its worker processes die too, nothing they computed is
committed, and the restarted server removes the job's staging folder."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

from acquisition.patterns import build_plan
from hw_mocks.cameras import mild_pinhole
from hw_mocks.poses import random_poses
from hw_mocks.synthetic import synthetic_maps
from tests.api_server import ROOT, ServerProcess


def descendants(pid: int) -> set[int]:
    """Every live process below `pid` (from /proc/<pid>/task/*/children)."""
    found: set[int] = set()
    todo = [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = [int(k) for k in (task / "children").read_text().split()]
            except OSError:
                continue
            for k in kids:
                if k not in found:
                    found.add(k)
                    todo.append(k)
    return found


def alive(pids: set[int]) -> set[int]:
    """The pids that still run (zombies count as gone)."""
    out = set()
    for p in pids:
        try:
            state = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            out.add(p)
    return out


def wait_gone(pids: set[int], timeout_s: float = 15.0) -> set[int]:
    """Wait for `pids` to exit; SIGKILL (and return) the survivors so no test leaves any."""
    deadline = time.monotonic() + timeout_s
    while alive(pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = alive(pids)
    for p in left:
        os.kill(p, signal.SIGKILL)
    return left


def import_synthetic_session(c: httpx.Client, n_poses: int = 3) -> str:
    """A session whose poses are exact synthetic maps (hw_mocks) imported as NPZ."""
    plan = build_plan(640, 480, 0.5, preset="fast")
    sess = c.post("/sessions", json={"plan": plan.to_dict()}).json()
    cam = mild_pinhole(320, 240)
    rng = np.random.default_rng(7)
    for k, pose in enumerate(random_poses(cam, plan.screen, n_poses, rng)):
        maps, _ = synthetic_maps(cam, pose, plan.screen, sigma_px=0.05, rng=rng, pose_id=f"s{k}")
        maps.meta["plan_digest"] = plan.digest()
        r = c.post(f"/sessions/{sess['id']}/poses/import-maps",
                   files={"file": ("maps.npz", maps.to_npz_bytes())})
        assert r.status_code == 201, r.text
    return sess["id"]


def test_kill9_mid_fit_leaves_no_worker_and_no_committed_output(tmp_path: Path) -> None:
    data = tmp_path / "data"
    srv = ServerProcess(data)
    srv.start()
    assert srv.proc is not None
    children = descendants(srv.proc.pid)
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            sid = import_synthetic_session(c)
            job = c.post(f"/sessions/{sid}/calibrations", json={"model": "sgcc"}).json()
            deadline = time.monotonic() + 120
            while True:
                j = c.get(f"/jobs/{job['id']}").json()
                assert j["status"] in ("queued", "running"), j
                if j["stage"] not in ("queued", "starting", "load"):
                    break  # the fit runs in a worker process
                assert time.monotonic() < deadline
                time.sleep(0.02)
        children |= descendants(srv.proc.pid)
        assert len(children) >= 3, children  # worker processes, manager, resource tracker
        srv.kill()
    finally:
        srv.kill()
        orphans = wait_gone(children)
    assert not orphans, f"worker processes outlived the killed server: {sorted(orphans)}"
    cal_id = job["resource"].rsplit("/", 1)[-1]
    time.sleep(1.0)  # an orphan would have kept writing by now
    assert not (data / "calibrations" / cal_id / "model.json").exists()
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert c.get(f"/jobs/{job['id']}").json()["status"] == "interrupted"
            cal = c.get(f"/calibrations/{cal_id}").json()
            assert cal["status"] == "interrupted" and cal["exports"] == []
        assert list((data / "tmp").iterdir()) == []  # stale staging removed at restart
    finally:
        children = descendants(srv.proc.pid) if srv.proc else set()
        srv.stop()
        assert not wait_gone(children), "a gracefully stopped server left processes running"


def _run_python(code: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *(["-c", code] if code else []), *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_an_unused_process_executor_stops_and_exits() -> None:
    """Workers spawned up front are stopped by shutdown() and at interpreter exit (they hung
    both when the pool's manager thread had never started)."""
    code = ("from api.worker.executor import ProcessExecutor\n"
            "ProcessExecutor().shutdown(wait=False)\n"
            "ProcessExecutor()\n")
    done = _run_python(code)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr


def test_serve_with_a_bad_rigs_dir_exits_1(tmp_path: Path) -> None:
    done = _run_python("", "-m", "api.cli", "serve", "--port", "1", "--data-dir",
                       str(tmp_path / "d"), "--rigs-dir", str(tmp_path / "missing"))
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        f"phasecal serve: error: --rigs-dir {tmp_path / 'missing'}: no such folder"]


def test_ctrl_c_stops_the_server_and_its_workers_without_tracebacks(tmp_path: Path) -> None:
    """A terminal's Ctrl-C sends SIGINT to the whole process group: the server shuts down in
    order, its worker processes exit with it, and nothing prints a traceback."""
    from api.inprocess import free_port

    port = free_port()
    env = {k: v for k, v in os.environ.items() if k != "PHASECAL_DASK"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "api.cli", "serve", "--port", str(port), "--executor",
         "processes", "--data-dir", str(tmp_path / "data")],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True)
    children: set[int] = set()
    try:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/health", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                time.sleep(0.1)
        children = descendants(proc.pid)
        assert len(children) >= 2, "expected worker processes"
        os.killpg(proc.pid, signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert "Traceback" not in out and "KeyboardInterrupt" not in out, out
    assert not wait_gone(children), "Ctrl-C left processes running"
