"""Figures drawn from several threads at once come out as when drawn one after another
(matplotlib's text layout is not thread-safe: `calibration.figures.one_at_a_time`)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from calibration.report_plots import count_png


def test_log_scale_figures_drawn_by_threads_equal_serial_ones() -> None:
    rng = np.random.default_rng(3)
    counts = [rng.integers(0, 3 + k % 4, size=(60, 80)) for k in range(12)]
    serial = [count_png(c, f"coverage $10^{{{k}}}$") for k, c in enumerate(counts)]
    with ThreadPoolExecutor(6) as pool:
        threaded = list(pool.map(lambda kc: count_png(kc[1], f"coverage $10^{{{kc[0]}}}$"),
                                 enumerate(counts)))
    assert all(png[:4] == b"\x89PNG" for png in threaded)
    assert threaded == serial
