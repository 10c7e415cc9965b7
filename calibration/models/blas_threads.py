"""Single-threaded BLAS for the spline code: its matrix products are small, threads only contend.

Measured on the loaded 2-core build machine with OpenBLAS's default two threads: a ~500x500
Cholesky took 0.21 s per call; a 2 M-point spline evaluation 2.3 s (0.46 s with one thread).
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits


def single_thread_blas() -> threadpool_limits:
    """Context manager limiting BLAS to one thread for the duration of a `with` block."""
    return threadpool_limits(1, user_api="blas")
