"""Threads over cache-sized chunks of NumPy work: NumPy releases the GIL inside its loops,
so one thread per core this process may use (at most `MAX_THREADS`: more only contend)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

MAX_THREADS = 4


def thread_count(items: int) -> int:
    """Threads for `items` pieces of work: the CPUs this process may use, at most one each."""
    return max(1, min(items, len(os.sched_getaffinity(0)), MAX_THREADS))


def map_in_threads(fn: Callable[[Any], Any], items: Sequence[Any]) -> list[Any]:
    """`fn` over `items`, results in their order; in this thread when one thread suffices."""
    n = thread_count(len(items))
    if n == 1:
        return [fn(item) for item in items]
    with ThreadPoolExecutor(n) as pool:
        return list(pool.map(fn, items))
