"""DaskExecutor against a real LocalCluster: same results as in-process, progress, cancel,
worker death survived or failed cleanly, data by reference."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import cloudpickle
import dask
import distributed
import numpy as np
import pytest

from api.worker.dask_context import cancel_event_name
from api.worker.dask_executor import DaskExecutor, WorkerLost
from api.worker.executor import InProcessExecutor, make_executor
from calibration.shared.progress import Cancelled, TaskContext

# Task functions below are defined in this test module, which workers cannot import.
cloudpickle.register_pickle_by_value(sys.modules[__name__])

RESULT_TIMEOUT_S = 60.0


def fit_plane_task(ctx: TaskContext, points_path: str, out_path: str) -> dict:
    """Least-squares plane through points read from a file; result written atomically."""
    pts = np.load(points_path)
    ctx.progress(0, 2, "fit")
    design = np.column_stack([pts[:, 0], pts[:, 1], np.ones(len(pts))])
    coef, *_ = np.linalg.lstsq(design, pts[:, 2], rcond=None)
    resid = pts[:, 2] - design @ coef
    tmp = out_path + ".tmp.npy"
    np.save(tmp, np.concatenate([coef, resid]))
    os.replace(tmp, out_path)
    ctx.progress(2, 2, "fit")
    return {"rms": float(np.sqrt(np.mean(resid**2))), "n": len(pts)}


def counting_task(ctx: TaskContext, n: int, pause_s: float) -> int:
    """Reports progress n times."""
    for i in range(n):
        time.sleep(pause_s)
        ctx.progress(i + 1, n, "count")
    return n


def wait_for_cancel_task(ctx: TaskContext, started_path: str, limit_s: float) -> str:
    """Polls cancelled() until set; returns 'timeout' if nobody cancels within limit_s."""
    Path(started_path).write_text(str(os.getpid()))
    t_end = time.monotonic() + limit_s
    while time.monotonic() < t_end:
        if ctx.cancelled():
            Path(started_path + ".end").write_text("cancelled")
            raise Cancelled(ctx.job_id)
        time.sleep(0.02)
    Path(started_path + ".end").write_text("timeout")
    return "timeout"


def die_once_task(ctx: TaskContext, marker: str, hold_s: float) -> dict:
    """First attempt records its pid and waits to be killed; a retry finishes at once."""
    path = Path(marker)
    if not path.exists():
        path.write_text(str(os.getpid()))
        time.sleep(hold_s)
        return {"attempt": 1, "pid": os.getpid()}
    return {"attempt": 2, "pid": os.getpid()}


def always_die_task(ctx: TaskContext) -> None:
    """Kills its own worker process every time."""
    os.kill(os.getpid(), signal.SIGKILL)


def plain_add(a: int, b: int) -> int:
    """A plain callable for Executor.submit."""
    return a + b


@pytest.fixture(scope="module")
def cluster():
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        from api.worker.dask_executor import start_local_cluster

        lc = start_local_cluster(2)
        try:
            yield lc
        finally:
            lc.close()


@pytest.fixture(scope="module")
def dex(cluster):
    ex = DaskExecutor(cluster.scheduler_address, cancel_poll_s=0.05)
    yield ex
    ex.shutdown(wait=False)


def _wait_file(path: Path, limit_s: float = 30.0) -> str:
    t_end = time.monotonic() + limit_s
    while time.monotonic() < t_end:
        if path.exists() and path.read_text():
            return path.read_text()
        time.sleep(0.02)
    raise AssertionError(f"{path} was not written within {limit_s} s")


def test_results_identical_to_in_process(dex, tmp_path):
    rng = np.random.default_rng(7)
    xy = rng.uniform(-50, 50, size=(5000, 2))
    z = 0.3 * xy[:, 0] - 1.7 * xy[:, 1] + 12.0 + rng.normal(0, 0.1, 5000)
    src = tmp_path / "points.npy"
    np.save(src, np.column_stack([xy, z]))
    local = InProcessExecutor(max_workers=1)
    try:
        a = local.run_task(fit_plane_task, str(src), str(tmp_path / "a.npy"), job_id="job-a")
        summary_local = a.result(RESULT_TIMEOUT_S)
    finally:
        local.shutdown()
    b = dex.run_task(fit_plane_task, str(src), str(tmp_path / "b.npy"), job_id="job-b")
    summary_dask = b.result(RESULT_TIMEOUT_S)
    assert summary_dask == summary_local
    assert np.array_equal(np.load(tmp_path / "a.npy"), np.load(tmp_path / "b.npy"))
    assert dex.running_jobs() == []


def test_submit_plain_callable(dex):
    assert dex.submit(plain_add, 2, b=40).result(RESULT_TIMEOUT_S) == 42


def test_progress_reaches_the_client(dex):
    seen: list[tuple[int, int, str]] = []
    fut = dex.run_task(
        counting_task, 8, 0.1, job_id="job-progress", on_progress=lambda *m: seen.append(m)
    )
    assert fut.result(RESULT_TIMEOUT_S) == 8
    t_end = time.monotonic() + 10
    while (8, 8, "count") not in seen and time.monotonic() < t_end:
        time.sleep(0.02)
    assert (8, 8, "count") in seen
    assert len(seen) >= 4
    assert [d for d, _, _ in seen] == sorted(d for d, _, _ in seen)


def test_cancel_reaches_a_running_task(dex, tmp_path):
    started = tmp_path / "started"
    fut = dex.run_task(wait_for_cancel_task, str(started), 45.0, job_id="job-cancel")
    _wait_file(started)
    assert dex.cancel("job-cancel")
    with pytest.raises(Cancelled):
        fut.result(20.0)
    assert not dex.cancel("job-cancel")


def test_cancel_drops_a_queued_task(dex, tmp_path):
    blockers = [
        dex.run_task(wait_for_cancel_task, str(tmp_path / f"b{i}"), 45.0, job_id=f"job-block{i}")
        for i in range(2)
    ]
    for i in range(2):
        _wait_file(tmp_path / f"b{i}")
    queued = dex.run_task(counting_task, 1, 0.0, job_id="job-queued")
    assert dex.cancel("job-queued")
    with pytest.raises(Cancelled):
        queued.result(20.0)
    for i, b in enumerate(blockers):
        dex.cancel(f"job-block{i}")
        with pytest.raises(Cancelled):
            b.result(20.0)


def test_killed_worker_is_survived(dex, tmp_path):
    marker = tmp_path / "attempt1.pid"
    fut = dex.run_task(die_once_task, str(marker), 45.0, job_id="job-kill")
    pid = int(_wait_file(marker))
    os.kill(pid, signal.SIGKILL)
    result = fut.result(RESULT_TIMEOUT_S)
    assert result["attempt"] == 2
    assert result["pid"] != pid


def test_repeated_worker_death_fails_with_a_reason(dex):
    fut = dex.run_task(always_die_task, job_id="job-die")
    with pytest.raises(WorkerLost, match="always_die_task of job job-die: its worker died"):
        fut.result(RESULT_TIMEOUT_S)
    assert "job-die" not in dex.running_jobs()
    # the cluster still works afterwards
    assert dex.submit(plain_add, 1, 1).result(RESULT_TIMEOUT_S) == 2


def test_large_arrays_are_refused(dex):
    big = np.zeros((1024, 1024), dtype=np.float32)
    with pytest.raises(ValueError, match="pass its path"):
        dex.run_task(counting_task, big, 0.0, job_id="job-big")
    with pytest.raises(ValueError, match="pass its path"):
        dex.run_task(counting_task, 1, 0.0, job_id="job-big2", extra=[big])
    assert dex.running_jobs() == []


def test_duplicate_job_id_is_refused(dex, tmp_path):
    fut = dex.run_task(wait_for_cancel_task, str(tmp_path / "s"), 45.0, job_id="job-dup")
    with pytest.raises(ValueError, match="already running"):
        dex.run_task(counting_task, 1, 0.0, job_id="job-dup")
    dex.cancel("job-dup")
    with pytest.raises(Cancelled):
        fut.result(20.0)


def test_task_cancelled_before_it_started_stops_if_it_runs_anyway(dex, tmp_path):
    started = tmp_path / "s"
    fut = dex.run_task(wait_for_cancel_task, str(started), 45.0, job_id="job-early")
    dex.cancel("job-early")
    with pytest.raises(Cancelled):
        fut.result(20.0)
    # the flag stays set: Client.cancel cannot stop a task a worker has already begun
    flag = distributed.Event(cancel_event_name("job-early"), client=dex.client)
    assert flag.is_set()
    # one task pinned to each single-threaded worker runs only after a leftover task ended
    workers = list(dex.client.scheduler_info()["workers"])
    probes = [dex.client.submit(plain_add, 1, 1, workers=[w], pure=False) for w in workers]
    assert dex.client.gather(probes) == [2] * len(workers)
    if started.exists():
        assert _wait_file(Path(str(started) + ".end")) == "cancelled"


def test_make_executor_uses_dask_for_tcp(cluster, monkeypatch):
    monkeypatch.setenv("PHASECAL_DASK", cluster.scheduler_address)
    ex = make_executor()
    try:
        assert isinstance(ex, DaskExecutor)
        assert ex.address == cluster.scheduler_address
        assert ex.run_task(counting_task, 2, 0.0, job_id="job-env").result(RESULT_TIMEOUT_S) == 2
    finally:
        ex.shutdown()
    with pytest.raises(RuntimeError, match="shut down"):
        ex.submit(plain_add, 1, 2)


def test_unreachable_scheduler_names_the_fix():
    with pytest.raises(ConnectionError, match="dask scheduler"):
        DaskExecutor("tcp://127.0.0.1:9", timeout_s=1.0)


def test_bad_local_address():
    with pytest.raises(ValueError, match="local:N"):
        DaskExecutor("local:zero")

