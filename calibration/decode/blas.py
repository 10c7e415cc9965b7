"""One BLAS thread for the decoder's small dense solves (the noise line's least squares,
~1e5 x 8): OpenBLAS's second thread gains nothing there, and after each call it spins
(~0.05 CPU s per 5 MP finish) on the core the finish's pixel threads need next.
(calibration.models.blas_threads does the same for the model fits, with SciPy's BLAS.)"""

from __future__ import annotations

import functools
from contextlib import AbstractContextManager
from typing import Any


@functools.cache
def _controller() -> Any:
    """The BLAS libraries loaded at the first call (NumPy's), scanned once (~2 ms)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def one_blas_thread() -> AbstractContextManager:
    """Context manager limiting BLAS to one thread for the duration of a `with` block."""
    return _controller().limit(limits=1, user_api="blas")
