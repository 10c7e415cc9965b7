"""Load (or compile, once per machine) the decoder's numba kernels before they are needed."""

from __future__ import annotations

import contextlib
import fcntl
import functools
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np


@functools.lru_cache(maxsize=1)
def warm_up() -> None:
    """Run each kernel on a few pixels with the argument types a uint8 camera's decode
    passes (a live capture does this while frames arrive, not after the last one); where
    they are not compiled yet, one process of the install compiles them while the others
    wait for its cache (`compiled_once`)."""
    from calibration.decode.kernel_sums import finish_sums

    with compiled_once(getattr(getattr(finish_sums, "_cache", None), "cache_path", None)):
        _run_kernels()


@contextlib.contextmanager
def compiled_once(folder: str | os.PathLike | None) -> Iterator[None]:
    """Run the body (which loads or compiles the kernels cached in `folder`) so that the
    processes of one install compile them one at a time: the first takes a lock beside
    the cache and compiles, the others wait and then load its machine code (two service
    workers of a fresh install used to compile the same kernels at once: twice the ~2 CPU
    minutes). Once a run has finished, a mark with the kernels' sources digest, numba's
    and Python's versions lets every later process load without taking the lock. Without
    a writable folder (numba then compiles in memory) the body just runs."""
    if folder is None:
        yield
        return
    import numba

    from calibration.decode.kernel_cache import sources_digest

    folder = Path(folder)
    mark = folder / "kernels.warm"
    stamp = f"{sources_digest()} numba {numba.__version__} python {sys.version.split()[0]}"
    try:
        warm = mark.read_text() == stamp
    except OSError:
        warm = False
    if warm:
        yield
        return
    try:
        lock = open(folder / "kernels.lock", "a")
    except OSError:
        yield
        return
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        yield
        with contextlib.suppress(OSError):
            part = folder / f"kernels.warm.{os.getpid()}"
            part.write_text(stamp)
            part.replace(mark)


def _run_kernels() -> None:
    """`warm_up`'s calls: every kernel with a uint8 decode's argument types."""
    from calibration.decode.accumulate_kernel import NO_CLIP_HI, accumulate_block
    from calibration.decode.finish import output_planes
    from calibration.decode.kernel import warm_up as warm_finish
    from calibration.decode.kernel_clipped import unknown_patterns
    from calibration.decode.kernel_sums import finish_sums, residual_stats
    from calibration.decode.ptc_kernels import warm_up as warm_noise_line

    warm_finish()
    warm_noise_line()  # (the noise line's passes after the last frame)
    # and its least squares on one BLAS thread: threadpoolctl's import and first library
    # scan (~13 ms), otherwise paid by a worker's first pose after its last frame
    from calibration.models.blas_threads import single_thread_blas

    with single_thread_blas(scipy=False):
        np.linalg.lstsq(np.ones((4, 2)), np.ones(4), rcond=None)
    n = 4
    frames = np.ones((1, n), dtype=np.uint8)
    i64 = functools.partial(np.zeros, dtype=np.int64)
    one = np.ones(1, dtype=np.int64)
    weights = np.ones((1, 3, 1), dtype=np.float32)
    sums = np.zeros((3, n), np.float32)
    for bits_dtype in (np.uint8, np.uint16):
        bits = np.zeros((1, n), bits_dtype)
        for squares in (np.zeros(n, np.float32), np.zeros(0, np.float32)):
            flats = np.zeros((2, n))
            accumulate_block(frames, i64(1), np.full(1, 3), i64(1), i64(1), weights, i64(1),
                             one * 3, 0.0, NO_CLIP_HI, 0, 0, n, sums, bits, squares, flats[0],
                             flats[1], np.zeros(1), i64(1))
            planes = [output_planes(n, ["x", "y"])[name] for name in  # (their strides)
                      ("position", "sigma", "modulation", "blur")]
            tables = (np.full((1, 16), -1), np.zeros((0, 30)), np.zeros((1, 4, 3)), i64(1))
            unknown_patterns(bits, 0, n, tables[0], one * 4)
            finish_sums(sums, bits, squares, flats[0], flats[1], 0, i64(1), one * 3, one * 4,
                        np.array([0.0, 1, 0, 0, 0, 0.1, 0]), np.zeros(3), np.zeros(1), np.ones(2),
                        np.full(2, np.inf), i64(1), np.ones(1), np.ones(1), np.full(2, np.inf),
                        np.ones(2), np.ones(7), *planes, 0, np.zeros(n, np.uint8), tables)
            if squares.size:
                out = [np.zeros(n, np.float32) for _ in range(3)]
                residual_stats(sums, bits, squares, 0, i64(1), one * 3, one * 4, *out,
                               np.zeros(n, np.bool_), np.zeros((1, n), np.float32),
                               np.zeros(n, np.bool_), flats[0], flats[1], np.ones(5),
                               np.zeros(1), tables)


if __name__ == "__main__":  # `make setup`: compile once per checkout, not in the first capture
    warm_up()
