"""calibration.models.heap: freed memory stays mapped inside the block (glibc), nesting."""

from __future__ import annotations

import subprocess
import sys

import pytest

from calibration.models import heap

_PROBE = """
import resource
import numpy as np
from calibration.models import heap

def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

def burst(n):  # allocate 4 arrays of n float64 again after freeing 4 such arrays
    arrays = [np.ones(n) for _ in range(4)]
    del arrays
    before = faults()
    arrays = [np.ones(n) for _ in range(4)]
    return faults() - before

n = 2_500_000  # 20 MB each: glibc trims the 80 MB freed at once, then faults them in again
outside = burst(n)
with heap.retained_heap():
    inside = burst(n)
print(outside, inside)
"""


@pytest.mark.skipif(heap._LIBC is None, reason="mallopt/malloc_trim are glibc's")
def test_freed_arrays_are_reused_without_page_faults_inside_the_block():
    # A fresh interpreter: the allocator's state in a long test session is not predictable.
    out = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                         check=True).stdout
    outside, inside = map(int, out.split())
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
