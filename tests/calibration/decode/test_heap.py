"""A decoding worker keeps the heap memory it frees (`heap`), so a finish's temporaries
reuse warm pages instead of faulting in new ones; the noise line's least squares run on one
BLAS thread (`models.blas_threads`)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import threadpoolctl

from calibration.decode import heap
from calibration.decode.noise import residual_line
from calibration.models.blas_threads import single_thread_blas

# Allocate, write and free blocks of a size glibc maps afresh by default (1.5 MB, under
# NumPy's 4 MB huge-page threshold, so every 4 KB page is a fault), many times over: page
# faults counted in this thread.
_FAULTS = textwrap.dedent("""
    import resource, sys
    import numpy as np
    from calibration.decode import heap
    if sys.argv[1] == "warm":
        assert heap.warm_heap() and not heap.warm_heap()
    elif sys.argv[1] == "trimmed":  # a fit in between handed the free heap back
        from calibration.models.heap import retained_heap
        assert heap.warm_heap()
        with retained_heap():
            pass
        assert heap.warm_heap() and not heap.warm_heap()
    elif sys.argv[1] == "retain":
        assert heap.retain_freed_memory()
    faults = lambda: resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
    for _ in range(3):  # (the first round may take pages the heap has not had yet)
        before = faults()
        for _ in range(20):
            blocks = [np.ones(3 << 19, dtype=np.uint8) for _ in range(4)]
            del blocks
    print(faults() - before)
""")


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True,
                         check=True)
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt")
def test_freed_memory_is_reused_without_page_faults():
    default, retained, warmed = _faults("default"), _faults("retain"), _faults("warm")
    assert default > 1000  # 80 blocks of 384 pages: glibc hands most of them back
    assert retained < 50
    assert warmed < 50
    assert _faults("trimmed") < 50  # warmed again after a fit's malloc_trim


# Four threads at once allocate, write and free 96 MB each in 24 MB blocks (a rig's four
# finishes), round after round: page faults of the process per round.
_THREADS = textwrap.dedent("""
    import resource, threading
    import numpy as np
    from calibration.decode import heap
    assert heap.retain_freed_memory(4)
    def work():
        blocks = [np.ones(24 << 20, dtype=np.uint8) for _ in range(4)]
        del blocks
    faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    rounds = []
    for _ in range(5):
        before = faults()
        threads = [threading.Thread(target=work) for _ in range(4)]
        [t.start() for t in threads]
        [t.join() for t in threads]
        rounds.append(faults() - before)
    print(min(rounds[1:]))
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc arenas")
def test_concurrent_decodes_keep_their_freed_memory_in_one_arena(monkeypatch):
    """glibc gives threads arenas of 64 MB heaps and deletes a heap that becomes free
    whatever the trim threshold: concurrent finishes faulted their temporaries in afresh
    every pose. Workers run in one arena (`one_heap_arena`), which keeps them."""
    def faults(env: dict[str, str]) -> int:
        out = subprocess.run([sys.executable, "-c", _THREADS], capture_output=True, text=True,
                             check=True, env=env)
        return int(out.stdout.split()[-1])

    monkeypatch.delenv(heap.ARENA_VAR, raising=False)
    base = dict(os.environ)
    with heap.one_heap_arena():
        one_arena = dict(os.environ)
    assert one_arena[heap.ARENA_VAR] == "1" and heap.ARENA_VAR not in os.environ
    assert faults(base) > 1000  # 16 blocks of 6144 pages: whole heaps handed back
    assert faults(one_arena) < 100


def test_noise_line_runs_on_one_blas_thread(monkeypatch):
    seen = []

    def lstsq(*args, **kwargs):
        seen.append(_blas_threads())
        return real(*args, **kwargs)

    real = np.linalg.lstsq
    monkeypatch.setattr(np.linalg, "lstsq", lstsq)
    rng = np.random.default_rng(3)
    level = rng.uniform(5, 200, 20000).astype(np.float32)
    dof = np.full(level.shape, 14.0, np.float32)
    rss = (dof * (0.3 + 0.02 * level) * rng.chisquare(14, level.shape) / 14).astype(np.float32)
    power = rng.uniform(0, 50, (2, level.size)).astype(np.float32)  # (no harmonic in rss)
    before = _blas_threads()
    line, leak = residual_line(level, rss, dof, power, 1 / 12, level)
    assert line is not None and abs(line.slope - 0.02) < 0.002 and leak is None
    assert seen and all(threads == [1] * len(threads) for threads in seen)
    assert _blas_threads() == before  # restored after the block
    with single_thread_blas(scipy=False):
        assert _blas_threads() == [1] * len(before)


def _blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpoolctl.threadpool_info()
            if lib["user_api"] == "blas"]
