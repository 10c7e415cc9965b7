"""A fresh service worker's first live decode, with and without the kernels loaded as the
worker starts (`ProcessExecutor(warm_kernels=...)`).

Run: .venv/bin/python benchmarks/worker_first_decode.py [--size 640x480] [--idle 5] [--runs 3]
For each setting and run: a new one-worker `ProcessExecutor`, `--idle` seconds without work
(a worker waiting for the first capture), then one task that decodes a pose as the live
path does (`StreamingDecoder(compiled=True)`: `prepare`, frames, `finish`) and returns the
task thread's CPU seconds and wall seconds. Medians over the runs; the CPU figure decides
(a shared machine's wall clock carries the other processes' share).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository's packages

from api.worker.executor import ProcessExecutor
from benchmarks.decode import bench_plan, make_stack
from calibration.decode import StreamingDecoder


def first_decode(stack: np.ndarray, shape: tuple[int, int]) -> tuple[float, float]:
    """In the worker: (thread CPU s, wall s) of one live-path decode of `stack`."""
    plan = bench_plan()
    cpu, wall = time.thread_time(), time.perf_counter()
    dec = StreamingDecoder(plan, shape, noise=1.0, compiled=True)
    dec.prepare()
    dec.add_frames(list(range(stack.shape[0])), stack)
    dec.finish()
    return time.thread_time() - cpu, time.perf_counter() - wall


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--idle", type=float, default=5.0)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    full = make_stack(bench_plan(), border=False)  # (the benchmark's 2448x2048 pose)
    stack = np.ascontiguousarray(full[:, :height, :width])
    results: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
    for _ in range(args.runs):
        for warm in (False, True):
            ex = ProcessExecutor(max_workers=1, warm_kernels=warm)
            try:
                time.sleep(args.idle)
                results[warm].append(ex.submit(first_decode, stack, (height, width)).result())
            finally:
                ex.shutdown()
    print(f"fresh worker's first decode, {width}x{height}, {stack.shape[0]} frames, idle "
          f"{args.idle:g} s before it; medians of {args.runs} (load "
          f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs)")
    print("kernels at worker start   task CPU s   task wall s")
    for warm in (False, True):
        cpu = statistics.median(r[0] for r in results[warm])
        wall = statistics.median(r[1] for r in results[warm])
        print(f"{'loaded' if warm else 'not loaded':<24}{cpu:11.3f}{wall:14.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
