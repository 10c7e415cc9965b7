"""Runs heavy decode/calibration work on an executor: threads by default, Dask when configured."""

from api.worker.executor import Executor, InProcessExecutor, make_executor

__all__ = ["Executor", "InProcessExecutor", "make_executor"]
