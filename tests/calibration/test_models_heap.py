"""calibration.models.heap: freed memory stays mapped inside the block (glibc), nesting."""

from __future__ import annotations

import resource

import numpy as np
import pytest

from calibration.models import heap


def _faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def _burst_faults(n: int) -> int:
    """Page faults of allocating 4 arrays of n float64 again after freeing 4 such arrays."""
    arrays = [np.ones(n) for _ in range(4)]
    del arrays
    before = _faults()
    arrays = [np.ones(n) for _ in range(4)]
    faults = _faults() - before
    del arrays
    return faults


@pytest.mark.skipif(heap._LIBC is None, reason="mallopt/malloc_trim are glibc's")
def test_freed_arrays_are_reused_without_page_faults_inside_the_block():
    n = 2_500_000  # 20 MB each: glibc trims the 80 MB freed at once, then faults them in again
    outside = _burst_faults(n)
    with heap.retained_heap():
        inside = _burst_faults(n)
    if outside < 100:  # huge pages everywhere: a few faults either way
        pytest.skip(f"only {outside} page faults without the block: nothing to compare")
    assert inside < outside / 10, (outside, inside)


def test_nested_and_concurrent_blocks_share_one_setting():
    with heap.retained_heap():
        with heap.retained_heap():
            assert heap._active == 2
        assert heap._active == 1
    assert heap._active == 0
    with pytest.raises(RuntimeError), heap.retained_heap():
        raise RuntimeError("the setting is restored on errors too")
    assert heap._active == 0
