"""A large live capture warms another worker's compiled decoder (`warm_decode_task`)."""

from __future__ import annotations

import sys

from calibration.worker.tasks import warm_decode_task


def test_warm_decode_task_loads_the_kernels_only_for_large_images() -> None:
    assert warm_decode_task(640 * 480) is False  # small images never use the kernels
    assert warm_decode_task(2448 * 2048) is True
    assert "calibration.decode.kernel_sums" in sys.modules
    assert "calibration.decode.accumulate_kernel" in sys.modules
