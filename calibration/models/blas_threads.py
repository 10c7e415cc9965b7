"""Single-threaded BLAS for small matrix products, where threads only contend: the spline
code, the dense fits and the decoder's noise-line least squares.

Measured on the loaded 2-core build machine with OpenBLAS's default two threads: a ~500x500
Cholesky took 0.21 s per call; a 2 M-point spline evaluation 2.3 s (0.46 s with one thread);
after the noise line's solve the second thread spun ~0.05 CPU s per 5 MP finish on the core
the finish's pixel threads needed next.
"""

from __future__ import annotations

import functools
from contextlib import AbstractContextManager

from threadpoolctl import ThreadpoolController


@functools.cache
def _controller(with_scipy: bool) -> ThreadpoolController:
    """The BLAS libraries loaded by then (with SciPy's, imported first when asked), scanned
    once: a scan costs ~2 ms, more than many small spline evaluations it wraps."""
    if with_scipy:
        import scipy.linalg  # noqa: F401  (SciPy bundles a BLAS of its own)
    return ThreadpoolController()


def single_thread_blas(*, scipy: bool = True) -> AbstractContextManager:
    """Context manager limiting BLAS to one thread for the duration of a `with` block;
    `scipy=False` limits the libraries loaded so far (NumPy's) without importing SciPy."""
    return _controller(scipy).limit(limits=1, user_api="blas")
