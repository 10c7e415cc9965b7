"""Single-threaded BLAS for the spline code: its matrix products are small, threads only contend.

Measured on the loaded 2-core build machine with OpenBLAS's default two threads: a ~500x500
Cholesky took 0.21 s per call; a 2 M-point spline evaluation 2.3 s (0.46 s with one thread).
"""

from __future__ import annotations

import functools
from contextlib import AbstractContextManager

import scipy.linalg  # noqa: F401  (SciPy's BLAS is loaded before the one scan below)
from threadpoolctl import ThreadpoolController


@functools.cache
def _controller() -> ThreadpoolController:
    """The BLAS libraries loaded at the first call (NumPy's, SciPy's and any other by then),
    scanned once: a scan costs ~2 ms, more than many small spline evaluations it wraps."""
    return ThreadpoolController()


def single_thread_blas() -> AbstractContextManager:
    """Context manager limiting BLAS to one thread for the duration of a `with` block."""
    return _controller().limit(limits=1, user_api="blas")
