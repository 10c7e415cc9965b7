"""The photon-transfer (noise) line fitted after a pose's last frame: `residual_line` on a
synthetic 5 MP-like noise sample.

Run: .venv/bin/python benchmarks/noise_line.py [--repeats N] [--pixels N]
The decoder fits it on ~0.3 M sampled pixels' residuals, serially, between the last frame
and the pose being ready. The sample is generated here: levels 0..250 DN (means of 8-bit
steps), 30-44 residual degrees of freedom, a photon-transfer variance (read 0.6 DN, 4 e/DN),
a display harmonic on 6 fringe sets (gamma without LUT) and a few model errors. Prints ms
per call (best and median wall, CPU) for the product code with its compiled passes (numba
loaded and freed memory kept, as in a decode worker), for its NumPy path (a process
without numba), and for the reference code kept in the tests (tests/calibration/decode/
ptc_reference.py, when the tests are present), with the ratio to it and whether all three
give the same line and harmonic.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration.decode import noise, ptc_select
from calibration.decode.heap import retain_freed_memory
from calibration.decode.noise import residual_line


def sample(pixels: int, seed: int = 1) -> tuple:
    """`residual_line`'s arguments for a synthetic sample of `pixels` pixels."""
    rng = np.random.default_rng(seed)
    level = np.round(rng.uniform(0.0, 250.0, pixels) * 6.0) / 6.0
    dof = rng.integers(30, 45, pixels).astype(np.float64)
    var = 0.6**2 + 1.0 / 12.0 + level / 4.0
    steps = 6.0
    b = rng.uniform(40.0, 120.0, (6, pixels))  # fringe amplitude per set (DN)
    phi = rng.uniform(0.0, 2.0 * np.pi, (6, pixels))
    power = steps * b**2 * np.cos(steps * phi / 2.0) ** 2  # noise.nyquist_power_of
    r2 = np.array([8e-4, 6e-4, 0.0, 7e-4, 1e-4, 0.0])  # the harmonic ratios squared
    rss = var * rng.chisquare(dof) + r2 @ power
    rss[rng.random(pixels) < 1e-3] *= 30.0  # model errors
    dark = rng.normal(2.0, 0.3, pixels)
    f32 = (level, rss, dof, np.asfortranarray(power), dark)
    level, rss, dof, power, dark = (a.astype(np.float32) for a in f32)
    return level, rss, dof, power, 1.0 / 12.0, dark


def timed(fn, args: tuple, repeats: int) -> tuple[float, float, float, object]:
    """Best and median wall ms and mean CPU ms per call, and the result."""
    result = fn(*args)  # (loads what it needs)
    walls, cpu = [], time.process_time()
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(*args)
        walls.append(time.perf_counter() - t0)
    cpu = (time.process_time() - cpu) / repeats
    return 1e3 * min(walls), 1e3 * float(np.median(walls)), 1e3 * cpu, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--pixels", type=int, default=300_000)
    opts = parser.parse_args()
    args = sample(opts.pixels)
    from calibration.decode import ptc_kernels

    ptc_kernels.warm_up()  # numba loaded, its cached kernels in memory: a decoding process
    retain_freed_memory()  # (as a decode worker: temporaries without fresh page faults)
    rows = [("product, compiled passes", residual_line)]

    def numpy_path(*a):
        """The product code with the compiled passes off (a process without numba)."""
        saved = ptc_select.compiled, noise.compiled
        ptc_select.compiled = noise.compiled = lambda: None
        try:
            return residual_line(*a)
        finally:
            ptc_select.compiled, noise.compiled = saved

    rows.append(("product, NumPy path", numpy_path))
    try:
        from tests.calibration.decode.ptc_reference import residual_line as before
    except ImportError:  # (an installed copy without the tests)
        before = None
    if before is not None:
        rows.append(("before 15g (reference)", before))
    print(f"noise line on {opts.pixels} pixels, 6 sets, best of {opts.repeats}; "
          f"load {' '.join(f'{x:.2f}' for x in os.getloadavg())}; {os.cpu_count()} CPUs")
    print(f"{'code':28s} {'best ms':>8s} {'median ms':>10s} {'CPU ms':>8s} {'x before':>9s}")
    results, times = [], []
    for name, fn in rows:
        best, median, cpu, result = timed(fn, args, opts.repeats)
        results.append(result)
        times.append((name, best, median, cpu))
    base = times[-1][3] if before is not None else None
    for name, best, median, cpu in times:
        ratio = f"{cpu / base:9.2f}" if base else f"{'-':>9s}"
        print(f"{name:28s} {best:8.1f} {median:10.1f} {cpu:8.1f} {ratio}")
    line, leak = results[0]
    same = all(r == results[0] for r in results)
    print(f"line offset {line.offset:.6g} slope {line.slope:.6g}; harmonic r^2 {leak}; "
          f"identical results: {'yes' if same else 'NO'}")
    if not same:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
