"""SIGTERM and SIGINT to `phasecal serve` mid-capture: an orderly stop; and the parts it
rests on (every close step runs, a dead manager or worker raises nothing, workers ignore
the service's stop signals but not their server's).

The server (default 'processes' executor, simulated rig) is stopped three ways an operator
meets: SIGTERM to the server alone (`kill PID`, systemd with KillMode=mixed), SIGTERM to
every process of the service (systemd's default KillMode=control-group, `kill -TERM -PGID`)
and SIGINT to the whole process group (a terminal's Ctrl-C). Each must exit 0 without
"Application shutdown failed" or a traceback, leave no worker process behind, store the
capture job and its pose as `interrupted` with a reason, and let a restarted server resume
the pose to the end.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from api.config import ServiceConfig
from api.db import Database
from api.demo import demo_rig_config
from api.inprocess import free_port
from api.jobs.manager import JobManager
from api.services import Services
from api.worker.executor import InProcessExecutor
from calibration.shared.plan import ScreenGeometry
from calibration.shared.progress import TaskContext
from tests.api.test_api_lifetime import alive, descendants, wait_gone
from tests.api.test_api_units import FnJob
from tests.api_server import ROOT, ServerProcess

#: (signal, sent to the whole process group)
CASES = {
    "sigterm-server": (signal.SIGTERM, False),
    "sigterm-group": (signal.SIGTERM, True),
    "sigint-group": (signal.SIGINT, True),
}


def start_serve(data: Path, log: Path) -> tuple[subprocess.Popen, str]:
    """`python -m api.cli serve` in its own session (its pid is its process group id), on a
    free loopback port, with the default executor; waits until /health answers."""
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k not in ("PHASECAL_DASK", "PHASECAL_DATA_DIR")}
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "api.cli", "serve", "--port", str(port), "--data-dir",
             str(data)], cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT,
            start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"server exited at start: {log.read_text()[-3000:]}")
        try:
            if httpx.get(f"{url}/health", timeout=1).status_code == 200:
                return proc, url
        except httpx.TransportError:
            time.sleep(0.1)
    proc.kill()
    raise AssertionError("server did not answer")


def start_capture(c: httpx.Client) -> dict:
    """A capture on a simulated rig slow enough (4x supersampled) to be stopped midway;
    its job (with the rig's id added as `rig_id`)."""
    screen = ScreenGeometry(320, 240, (0.5, 0.5))
    cfg = demo_rig_config(320, 240, camera="mild_pinhole", screen=screen)
    cfg["camera"]["supersample"] = 4
    rig = c.post("/rigs", json={"name": "slow", "config": cfg}).json()
    sess = c.post("/sessions", json={"rig_id": rig["id"], "preset": "fast"}).json()
    pose = {"rvec": [0.0, 0.0, 0.0], "tvec_mm": [-80.0, -60.0, 250.0]}
    r = c.post(f"/sessions/{sess['id']}/poses", json={"screen_pose": pose})
    assert r.status_code == 202, r.text
    return {**r.json(), "rig_id": rig["id"]}


def wait_job(c: httpx.Client, job_id: str, cond, timeout_s: float = 180.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        j = c.get(f"/jobs/{job_id}").json()
        if cond(j):
            return j
        time.sleep(0.05)
    raise AssertionError(f"job {job_id}: condition not reached ({j})")


def stored(db_path: Path, table: str, ident: str) -> tuple[str, str | None]:
    """(status, error) of one row, read from the database file itself."""
    with sqlite3.connect(db_path) as db:
        row = db.execute(f"SELECT status, error FROM {table} WHERE id = ?", (ident,)).fetchone()
    assert row is not None, f"{table} {ident} not stored"
    return row


@pytest.mark.parametrize("case", list(CASES))
def test_a_signal_mid_capture_stops_the_server_in_order(tmp_path: Path, case: str) -> None:
    sig, group = CASES[case]
    data, log = tmp_path / "data", tmp_path / "serve.log"
    proc, url = start_serve(data, log)
    children: set[int] = set()
    try:
        with httpx.Client(base_url=url, timeout=60) as c:
            job = start_capture(c)
            j = wait_job(c, job["id"], lambda j: j["done"] >= 3 or j["status"] != "running")
            assert j["status"] == "running" and j["stage"] == "capture", j
        children = descendants(proc.pid)
        assert len(children) >= 3, children  # worker processes, manager, resource tracker
        if group:
            os.killpg(proc.pid, sig)
        else:
            proc.send_signal(sig)
        proc.wait(90)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(30)
        orphans = wait_gone(children, timeout_s=5.0)
    out = log.read_text()
    assert proc.returncode == 0, out
    assert "shutdown failed" not in out.lower() and "Traceback" not in out, out
    assert not orphans, f"processes outlived the server: {sorted(orphans)}\n{out}"

    pose_id = job["resource"].rsplit("/", 1)[-1]
    for table, ident in (("jobs", job["id"]), ("poses", pose_id)):
        status, error = stored(data / "phasecal.db", table, ident)
        assert status == "interrupted", (table, status, error, out)
        assert error and "server shut down" in error, (table, error)

    srv = ServerProcess(data)
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert c.get(f"/jobs/{job['id']}").json()["status"] == "interrupted"
            r = c.post(f"{job['resource']}/resume")
            assert r.status_code == 202, r.text
            done = wait_job(c, r.json()["id"], lambda j: j["status"] not in ("queued", "running"))
            assert done["status"] == "succeeded", done
            pose = c.get(job["resource"]).json()
            assert pose["status"] == "ready", pose
    finally:
        srv.stop()


def test_open_streams_do_not_hold_the_stop(tmp_path: Path) -> None:
    """A client following the job (SSE) and one watching the camera (MJPEG) while SIGTERM
    comes: the job's stream ends with its `end` event, the preview ends, the server exits.
    (uvicorn waited for every open connection before the app's shutdown: the server never
    stopped while a preview was open.)"""
    proc, url = start_serve(tmp_path / "data", tmp_path / "serve.log")
    seen: dict[str, list[str]] = {"events": [], "preview": []}

    def follow(path: str, key: str) -> None:
        try:
            with httpx.stream("GET", f"{url}{path}", timeout=120) as resp:
                for line in resp.iter_lines():
                    seen[key].append(line)
        except httpx.HTTPError as exc:
            seen[key].append(f"error {type(exc).__name__}")
        seen[key].append("closed")

    try:
        with httpx.Client(base_url=url, timeout=60) as c:
            job = start_capture(c)
            wait_job(c, job["id"], lambda j: j["done"] >= 2 or j["status"] != "running")
        readers = [threading.Thread(target=follow, args=(path, key), daemon=True) for path, key
                   in ((f"/jobs/{job['id']}/events", "events"),
                       (f"/rigs/{job['rig_id']}/camera/preview?fps=2", "preview"))]
        for t in readers:
            t.start()
        deadline = time.monotonic() + 60
        while not all(seen.values()) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert all(seen.values()), seen  # both streams are open
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
        for t in readers:
            t.join(30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(30)
    out = (tmp_path / "serve.log").read_text()
    assert proc.returncode == 0, out
    assert "Traceback" not in out and "ERROR" not in out, out
    assert "event: end" in seen["events"], seen["events"][-5:]
    assert seen["preview"][-1] == "closed", seen["preview"][-3:]


# -- the parts ------------------------------------------------------------------------------
def wait_for_cancel(ctx: TaskContext) -> dict[str, Any]:
    """A task that reports once, then runs until its cancel flag is set."""
    ctx.progress(0, 1, "waiting")
    while not ctx.cancelled():
        time.sleep(0.01)
    return {}


def ignore_cancel(ctx: TaskContext, seconds: float) -> dict[str, Any]:
    """A task in one long step that never polls its cancel flag."""
    ctx.progress(0, 1, "busy")
    time.sleep(seconds)
    return {}


def run_python(code: str, timeout_s: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout_s)


class RefusingExecutor(InProcessExecutor):
    """Threads whose cancel and shutdown fail as a dead manager process makes them fail."""

    def cancel(self, job_id: str) -> bool:
        raise ConnectionRefusedError(111, "Connection refused")

    def shutdown(self, wait: bool = True) -> None:
        super().shutdown(wait)
        raise ConnectionRefusedError(111, "Connection refused")


def test_close_runs_every_step_when_the_executor_fails(tmp_path: Path) -> None:
    services = Services.build(ServiceConfig(data_dir=tmp_path / "data", executor="threads"))
    services.executor.shutdown()
    services.executor = RefusingExecutor(max_workers=1)
    closed: list[str] = []
    rigs_close, db_close = services.rigs.close, services.db.close
    services.rigs.close = lambda: (closed.append("rigs"), rigs_close())  # type: ignore[method-assign]
    services.db.close = lambda: (closed.append("db"), db_close())  # type: ignore[method-assign]
    services.close()
    assert closed == ["rigs", "db"]


def test_job_shutdown_interrupts_every_job_when_the_executor_cannot_cancel(
        tmp_path: Path) -> None:
    db = Database(tmp_path / "db.sqlite")
    executor = RefusingExecutor(max_workers=1)
    jm = JobManager(db, executor)
    ids = []
    for _ in range(2):
        running = threading.Event()

        def body(ctx: TaskContext, running: threading.Event = running) -> dict[str, Any]:
            running.set()
            while not ctx.cancelled():
                time.sleep(0.01)
            ctx.check_cancelled()
            return {}

        job = FnJob(body=body)
        with db.session() as s:
            state = jm.create(s, job)
        jm.start(state.id, job)
        assert running.wait(10)
        ids.append(state.id)
    jm.shutdown(timeout_s=30)
    for job_id in ids:
        got = jm.get(job_id)
        assert got is not None and got["status"] == "interrupted", got
        assert "server shut down" in got["error"]
    InProcessExecutor.shutdown(executor)


DEAD_MANAGER = """
import multiprocessing as mp, os, signal, threading
from api.worker.executor import ProcessExecutor
from tests.api.test_api_shutdown import wait_for_cancel
ex = ProcessExecutor(max_workers=1)
running = threading.Event()
fut = ex.run_task(wait_for_cancel, job_id="job_a", on_progress=lambda *a: running.set())
assert running.wait(60)
for p in mp.active_children():  # the worker and the manager, as a group's SIGKILL would
    os.kill(p.pid, signal.SIGKILL)
    p.join(10)
ex.cancel("job_a")
ex.shutdown(wait=False)
ex.shutdown(wait=False)
print("stopped", type(fut.exception(timeout=30)).__name__, flush=True)
"""


def test_a_process_executor_whose_processes_died_stops_quietly() -> None:
    done = run_python(DEAD_MANAGER)
    assert done.returncode == 0, done.stderr
    assert "stopped" in done.stdout and "Traceback" not in done.stderr, done.stderr


STUCK_WORKER = """
import multiprocessing as mp, threading, time
from api.worker.executor import ProcessExecutor
from tests.api.test_api_shutdown import ignore_cancel
ex = ProcessExecutor(max_workers=1)
ex.stop_grace_s = 1.0
running = threading.Event()
fut = ex.run_task(ignore_cancel, 600.0, job_id="job_a", on_progress=lambda *a: running.set())
assert running.wait(60)
workers = mp.active_children()
t0 = time.monotonic()
ex.shutdown(wait=False)
print("shutdown_s", round(time.monotonic() - t0, 2), flush=True)
print("alive", [p.pid for p in workers if p.is_alive()], flush=True)
"""


def test_shutdown_without_waiting_ends_a_worker_stuck_in_a_task() -> None:
    """No worker outlives `shutdown(wait=False)`: one in a step that never polls its cancel
    flag is killed after the grace (else it ran on, and interpreter exit waited for it)."""
    done = run_python(STUCK_WORKER, timeout_s=180)
    assert done.returncode == 0, done.stderr
    assert "alive []" in done.stdout, done.stdout + done.stderr
    assert "Traceback" not in done.stderr, done.stderr


SIGNALLED_WORKERS = """
import multiprocessing as mp, os, sys
from api.worker.executor import ProcessExecutor
ex = ProcessExecutor(max_workers=1)
children = mp.active_children()
print(*[p.pid for p in children], flush=True)
sys.stdin.readline()  # the test sends SIGTERM and SIGINT to every child meanwhile
print("task ran in", ex.submit(os.getpid).result(timeout=30), flush=True)
for p in children:  # the server's own terminate() (a broken pool's) is obeyed
    p.terminate()
    p.join(10)
print("exitcodes", *[p.exitcode for p in children], flush=True)
ex.shutdown(wait=False)
"""


def test_workers_ignore_the_services_stop_signals_but_obey_their_server() -> None:
    proc = subprocess.Popen([sys.executable, "-c", SIGNALLED_WORKERS], cwd=ROOT,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdin is not None
        pids = {int(p) for p in proc.stdout.readline().split()}
        assert len(pids) == 2, pids  # the worker and the manager
        for pid in pids:
            os.kill(pid, signal.SIGTERM)
            os.kill(pid, signal.SIGINT)
        time.sleep(1.0)
        assert alive(pids) == pids, "a worker died of a signal meant for the service"
        out, err = proc.communicate("\n", timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    ran_in = int(out.split("task ran in", 1)[1].split()[0])
    assert ran_in in pids
    assert "exitcodes -15 -15" in out, out + err


def worker_threads_and_blas() -> tuple[list[bool], int]:
    """In a worker: whether each of its threads has SIGTERM blocked (but the one that waits
    for it, where the wait opens it), and its BLAS threads."""
    import numpy as np  # noqa: F401  (loaded in every worker: its BLAS threads exist)
    from threadpoolctl import threadpool_info

    waiter = [t.native_id for t in threading.enumerate() if t.name == "phasecal-sigterm"]
    assert len(waiter) == 1, threading.enumerate()
    blocked = []
    for task in set(os.listdir("/proc/self/task")) - {str(waiter[0])}:
        status = Path(f"/proc/self/task/{task}/status").read_text()
        mask = int(status.split("SigBlk:")[1].split()[0], 16)
        blocked.append(bool(mask & (1 << (signal.SIGTERM - 1))))
    blas = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    return blocked, max(blas, default=1)


BLAS_WORKER = """
import json, os
from api.worker.executor import ProcessExecutor
from tests.api.test_api_shutdown import worker_threads_and_blas
ex = ProcessExecutor(max_workers=1)
blocked, blas = ex.submit(worker_threads_and_blas).result(timeout=60)
arena = ex.submit(os.getenv, "MALLOC_ARENA_MAX").result(timeout=60)
print(json.dumps([blocked, blas, os.environ.get("OPENBLAS_NUM_THREADS"), arena,
                  os.environ.get("MALLOC_ARENA_MAX")]), flush=True)
ex.shutdown(wait=False)
"""


@pytest.mark.parametrize(("blas", "arena"), [(None, None), ("3", "2")])
def test_every_worker_thread_blocks_sigterm_and_keeps_its_blas_threads(
        blas: str | None, arena: str | None) -> None:
    """OpenBLAS starts a thread per core when NumPy loads, before the worker's initializer:
    those threads would take a SIGTERM meant for the service by its default action (the
    worker dies mid-task). Workers start with one BLAS thread and get theirs back once
    SIGTERM is blocked: every thread then has it blocked, and a worker has the BLAS threads
    the server's environment asks for (one per core when it says nothing). Workers run in
    one heap arena unless the server's environment chose a count (`decode.heap`). The
    server's own environment is left as it was."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "MALLOC_ARENA_MAX")}
    if blas is not None:
        env["OPENBLAS_NUM_THREADS"] = blas
    if arena is not None:
        env["MALLOC_ARENA_MAX"] = arena
    done = subprocess.run([sys.executable, "-c", BLAS_WORKER], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr
    blocked, threads, after, worker_arenas, arenas_after = json.loads(
        done.stdout.splitlines()[-1])
    assert blocked and all(blocked), done.stdout
    assert threads == (int(blas) if blas else os.cpu_count()), done.stdout
    assert after == blas, done.stdout
    assert worker_arenas == (arena or "1") and arenas_after == arena, done.stdout
