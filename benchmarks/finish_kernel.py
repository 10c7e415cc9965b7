"""The compiled finish kernel (`kernel_sums.finish_sums`) against another revision's, A/B.

Run: .venv/bin/python benchmarks/finish_kernel.py [--against main] [--repeats 5]
     [--configs clean,partly,border] [--read-noise DN] [--gain E_PER_DN]
     [--frames F.npy --plan P.json]
Builds a 2448x2048 pose with the decode benchmark's generator (benchmarks/decode.py: its
64-frame plan and tilted-screen stack with its camera noise, by default hw_mocks' default
sensor), streams it into `StreamingDecoder` and records every `finish_sums` call of its
finish (the noise given: decode.py's camera model, 1.5 DN for a --frames pose; estimated
from the residuals (photon-transfer line); and the same calls with the pixels' own
residual variance). Then both kernels (this worktree's and `--against`'s,
imported from a `git archive` copy under another package name) decode each recorded
range in one thread, alternating call by call, `--repeats` times (each with the clipped
pixels' pattern tables built by its own kernel_clipped.py: the table layout may differ
between revisions); the table shows the sum
over the calls of each call's best thread CPU in ns per pixel (the pixels of every recorded
range), the ratio new / base, and whether the outputs make byte-identical maps (reason,
modulation; position, sigma, blur of valid pixels: the decoder masks the others). One
thread's CPU time: on a loaded machine, the ratio is the figure to trust.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from decode import H, W, bench_plan, given_noise, make_stack  # noqa: E402

import calibration.decode.kernel_clipped as kernel_clipped  # noqa: E402
import calibration.decode.kernel_sums as kernel_sums  # noqa: E402
from calibration.decode import StreamingDecoder  # noqa: E402
from calibration.decode.accumulate import FrameAccumulator  # noqa: E402
from calibration.decode.kernel_clipped import linear_line  # noqa: E402
from calibration.decode.kernel_sets import MODE_OWN  # noqa: E402
from calibration.shared.plan import read_plan  # noqa: E402

KERNEL_FILES = ("kernel.py", "kernel_sums.py", "kernel_sets.py", "kernel_unwrap.py",
                "kernel_clipped.py", "vecmath.py", "kernel_cache.py")
OUTPUTS = (20, 21, 22, 23)  # finish_sums argument positions: position, sigma, modulation, blur
O0, REASON, TABLES = 24, 25, 26  # (bits: 1, c0: 5)


def base_kernel(rev: str):
    """(`finish_sums`, its `kernel_clipped` module) of revision `rev`: its kernel files under
    a package named after their contents, in a folder kept between runs (numba's cache:
    compiled once per version), and the digest."""
    tree = subprocess.run(["git", "ls-tree", rev, "calibration/decode/"], cwd=ROOT, check=True,
                          capture_output=True, text=True).stdout
    blobs = {line.split()[3].rsplit("/", 1)[1]: line.split()[2] for line in tree.splitlines()}
    digest = hashlib.sha1(" ".join(blobs[f] for f in KERNEL_FILES).encode()).hexdigest()
    name = f"finish_base_{digest[:12]}"
    home = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "phasecal-bench"
    pkg = home / name
    if not (pkg / "kernel_sums.py").is_file():
        pkg.mkdir(parents=True, exist_ok=True)
        mods = "|".join(Path(f).stem for f in KERNEL_FILES)
        for f in KERNEL_FILES:
            text = subprocess.run(["git", "cat-file", "blob", blobs[f]], cwd=ROOT, check=True,
                                  capture_output=True, text=True).stdout
            text = re.sub(rf"calibration\.decode\.({mods})\b", rf"{name}.\1", text)
            (pkg / f).write_text(text)
        (pkg / "__init__.py").write_text("")
    sys.path.insert(0, str(home))
    module = __import__(f"{name}.kernel_sums", fromlist=["finish_sums"])
    clipped = __import__(f"{name}.kernel_clipped", fromlist=["pattern_tables"])
    return (module.finish_sums, clipped), digest[:12]


def with_own_tables(calls: list[tuple], clipped, plan, residual: bool) -> list[tuple]:
    """`calls` with their `tables` argument built by the kernel_clipped module `clipped`
    (revisions before `kernel_tables` take (index, rows, basis))."""
    sets = FrameAccumulator(plan, (1, 1), saturation_dn=None, need_squares=residual).sets
    tables = clipped.pattern_tables(sets)
    empty = clipped.no_tables() if hasattr(clipped, "no_tables") else (
        np.zeros((0, 1), np.int64), np.zeros((0, 1)), np.zeros((0, 1, 1)))
    out = []
    for a in calls:
        a = list(a)
        if a[TABLES][0].shape[0] == 0 or tables is None:
            a[TABLES] = empty
        elif hasattr(tables, "kernel_tables"):
            a[TABLES] = tables.kernel_tables(a[1], a[5], a[REASON].shape[0])
        else:
            a[TABLES] = (*tables.tables(a[1], a[5], a[REASON].shape[0]), tables.basis)
        out.append(tuple(a))
    return out


def pose(args: argparse.Namespace, config: str) -> tuple:
    """(plan, (F, H, W) uint8 stack) of one configuration (or the --frames file)."""
    if args.frames:
        return read_plan(args.plan), np.ascontiguousarray(np.load(args.frames))
    plan = bench_plan()
    return plan, make_stack(plan, border=config == "border", partly=config == "partly",
                            read_dn=args.read_noise, gain_e_per_dn=args.gain)


def record(plan, stack, noise) -> tuple[list[tuple], StreamingDecoder]:
    """The arguments of every finish_sums call of a streamed decode (the decoder is returned
    too: the calls read its sums)."""
    calls = []
    real = kernel_sums.finish_sums

    def keep(*a):
        calls.append(a)
        real(*a)

    dec = StreamingDecoder(plan, stack.shape[1:], noise=noise)
    dec.prepare()
    dec.add_frames(list(range(stack.shape[0])), stack)
    kernel_sums.finish_sums = keep
    try:
        dec.finish()
    finally:
        kernel_sums.finish_sums = real
    return calls, dec


def own_mode(calls: list[tuple]) -> list[tuple]:
    """The same calls with the pixels' own residual variance (noise mode MODE_OWN)."""
    out = []
    for a in calls:
        a = list(a)
        noise = np.array([MODE_OWN, 0.0, 0.0, 0.0, 0.0, a[9][5], -np.inf])
        a[9], a[10] = noise, linear_line(noise[[1, 2, 3, 4, 6]])
        out.append(tuple(a))
    return out


def call(kernel, a: tuple, outs: tuple) -> float:
    """Thread CPU seconds of `kernel` on the recorded arguments `a`, into the arrays `outs`."""
    a = list(a)
    a[20:24] = outs[0]
    a[REASON] = outs[1][a[O0]:a[O0] + a[REASON].shape[0]]
    t0 = time.thread_time()
    kernel(*a)
    return time.thread_time() - t0


def compare(calls: list[tuple], kernels: list, repeats: int, plan, residual: bool
            ) -> tuple[list[float], bool, int]:
    """Each kernel's CPU seconds over all calls (the sum of each call's best of `repeats`,
    the kernels alternating call by call), identical outputs, pixels."""
    npix = calls[0][20].shape[1]
    own = [with_own_tables(calls, clipped, plan, residual) for _, clipped in kernels]
    outs = []
    for _ in kernels:
        planes = [np.full((2, npix + 16), np.nan, calls[0][i].dtype)[:, :npix] for i in OUTPUTS]
        outs.append((planes, np.full(npix, 77, np.uint8)))
    best = np.full((len(kernels), len(calls)), np.inf)
    for rep in range(repeats):
        for c in range(len(calls)):
            order = range(len(kernels)) if (rep + c) % 2 == 0 else reversed(range(len(kernels)))
            for i in order:
                best[i, c] = min(best[i, c], call(kernels[i][0], own[i][c], outs[i]))
    return list(best.sum(axis=1)), same_maps(*outs), sum(a[REASON].shape[0] for a in calls)


def same_maps(old: tuple, new: tuple) -> bool:
    """Whether the two kernels' outputs make the same maps, byte for byte: reason codes and
    modulation everywhere, positions, sigmas and blur where valid (the decoder writes NaN
    elsewhere: its mask, as for dark ranges, dark_chunks.py)."""
    (planes_a, reason_a), (planes_b, reason_b) = old, new
    if reason_a.tobytes() != reason_b.tobytes():
        return False
    valid = reason_a == 0
    for i, (a, b) in enumerate(zip(planes_a, planes_b, strict=True)):
        if i != 2:  # (modulation: every pixel)
            a, b = np.where(valid, a, np.nan), np.where(valid, b, np.nan)
        if np.ascontiguousarray(a).tobytes() != np.ascontiguousarray(b).tobytes():
            return False
    return True


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", default="main", help="git revision of the base kernel")
    ap.add_argument("--new", help="git revision of the new kernel (default: the worktree)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--configs", default="clean,partly", help="clean, partly, border")
    ap.add_argument("--frames", help="a (F, H, W) uint8 .npy pose instead (with --plan)")
    ap.add_argument("--plan")
    ap.add_argument("--read-noise", type=float, default=0.08, metavar="DN",
                    help="the generated stacks' read noise (std, DN; as decode.py)")
    ap.add_argument("--gain", type=float, default=40.0, metavar="E_PER_DN",
                    help="the generated stacks' conversion gain (shot noise; as decode.py)")
    args = ap.parse_args()
    base, sha = base_kernel(args.against)
    new = base_kernel(args.new)[0] if args.new else (kernel_sums.finish_sums, kernel_clipped)
    kernels = [base, new]
    print(f"finish_sums A/B: base {args.against} (kernel files {sha}) vs "
          f"{args.new or 'worktree'}; "
          f"{'file ' + args.frames if args.frames else f'{W}x{H} generated'}; "
          f"load {os.getloadavg()[0]:.2f}; best of {args.repeats}, one thread")
    print(f"{'pose':>8} {'noise':>9} {'ranges':>6} {'Mpix':>5} {'base ns/px':>10} "
          f"{'new ns/px':>9} {'new/base':>8} identical")
    ok = True
    for config in ([Path(args.frames).stem] if args.frames else args.configs.split(",")):
        plan, stack = pose(args, config)
        noise = 1.5 if args.frames else given_noise(args, config == "partly")
        given, _ = record(plan, stack, noise)
        resid, dec = record(plan, stack, None)
        for label, calls in (("given", given), ("residual", resid), ("own", own_mode(resid))):
            t0 = time.perf_counter()
            best, same, npix = compare(calls, kernels, args.repeats, plan, label != "given")
            ok &= same
            print(f"{config:>8} {label:>9} {len(calls):>6} {npix / 1e6:>5.2f} "
                  f"{best[0] / npix * 1e9:>10.1f} {best[1] / npix * 1e9:>9.1f} "
                  f"{best[1] / best[0]:>8.3f} {'yes' if same else 'NO'}"
                  f"  ({time.perf_counter() - t0:.0f} s)", flush=True)
        del given, resid, dec, stack
    print(f"load {os.getloadavg()[0]:.2f}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
