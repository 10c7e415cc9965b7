"""The service's worker processes load the decoder's kernels as they start
(`ProcessExecutor(warm_kernels=True)`), so a fresh worker's first decode does not."""

from __future__ import annotations

import threading

import pytest

from api.worker import executor
from api.worker.executor import ProcessExecutor
from calibration.decode.kernel_sums import finish_sums


def kernels_loaded_once_idle() -> bool:
    """In a worker: wait for the start-up warm thread (if any), then whether the finish
    kernel has machine code loaded."""
    for thread in threading.enumerate():
        if thread.name == "phasecal-warm-kernels":
            thread.join(300)
    return bool(finish_sums.signatures)


@pytest.mark.parametrize("warm", [True, False])
def test_a_fresh_worker_loads_the_kernels_only_when_asked(warm: bool) -> None:
    ex = ProcessExecutor(max_workers=1, warm_kernels=warm)
    try:
        assert ex.submit(kernels_loaded_once_idle).result(timeout=300) is warm
    finally:
        ex.shutdown()


@pytest.mark.parametrize(("env", "warm"), [(None, True), ("0", False), ("1", True)])
def test_the_services_workers_warm_unless_turned_off(monkeypatch, env: str | None,
                                                     warm: bool) -> None:
    made: list[bool] = []
    monkeypatch.setattr(executor, "ProcessExecutor",
                        lambda warm_kernels: made.append(warm_kernels) or "pool")
    if env is None:
        monkeypatch.delenv(executor.WARM_ENV, raising=False)
    else:
        monkeypatch.setenv(executor.WARM_ENV, env)
    assert executor.make_executor("processes") == "pool" and made == [warm]
