"""Decoder throughput: a 2448x2048, 64-frame uint8 stack, versus a memory-bandwidth floor.

Run: .venv/bin/python benchmarks/decode.py [--xp numpy|cupy] [--repeats N] [--cli-only]
       [--breakdown] [--read-noise DN] [--gain E_PER_DN]
The stacks carry camera noise, by default that of hw_mocks' default sensor (10,000 e-
full well over 8 bits, 3 e- read noise: read 0.08 DN, 40 e-/DN, ~1.6 DN at mid grey;
`--read-noise 1.5 --gain 4`: a noisy camera, ~5 DN); the "noise given" rows get that
noise model, "noise from residuals" fits it. `--read-noise 0 --gain 0`: noise-free
stacks ("noise given": 1 DN).
Prints Mpixel-frames/s for the whole stack decoded at once (`decode_stack`: compiled,
cache-blocked accumulation and finish range by range, the goal's "end to end"), for the
streaming decoder frame by frame (`add`, `finish`, as a live capture runs it), and the
ratio to a NumPy sum over the same uint8 bytes measured on this machine; then finish
alone: Mpixel/s, its share of the pose's decode time and of the capture time.
Each stage also shows its CPU seconds (all threads): on a shared, loaded machine wall
times inflate, CPU seconds much less; `uptime`'s load is printed with the table (the
floor's CPU seconds too: on a loaded machine, compare configurations by CPU seconds).
Last, `phasecal decode` on the same stack in a fresh process against the library's read +
decode (best of N each), with the command's stage breakdown (`--timings`): startup,
imports, plan, read + decode (including the kernels' load), write, fsync, rename, summary.
`--breakdown` instead splits each configuration's `decode_stack` CPU seconds into the
accumulation kernel, the finish kernel and the rest (noise line, tables, Python).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from acquisition.patterns import build_plan
from calibration.decode import StreamingDecoder, batch, decode_stack, kernel_sums
from calibration.decode.noise import NoiseModel
from calibration.shared.plan import Plan, plan_from_dict

H, W = 2048, 2448
# (name, black border, partly clipped) of the stacks decoded
CONFIGS = (("no clipping", False, False), ("clipped border", True, False),
           ("partly clipped", False, True))
CAPTURE_HZ = 60.0  # display/camera rate the finish time is compared with


def bench_plan() -> Plan:
    """64 frames: 2 bright + 2 dark flats, 3 periods x 10 steps per axis."""
    base = build_plan(1920, 1080, 0.2745, steps=10, max_ratio=8.0, finest_period_px=48.0)
    data = base.to_dict()
    data["frames"] = [{"kind": "flat", "level": 1.0}, {"kind": "flat", "level": 0.0}] + data[
        "frames"
    ]
    plan = plan_from_dict(data)
    if len(plan.frames) != 64:
        raise SystemExit(f"benchmark plan has {len(plan.frames)} frames, expected 64")
    return plan


def black_dn(partly: bool) -> float:
    """The stacks' black level (DN)."""
    return 6.0 if partly else 20.0


def make_stack(plan: Plan, border: bool, partly: bool = False, read_dn: float = 0.0,
               gain_e_per_dn: float | None = None, seed: int = 0) -> np.ndarray:
    """Camera frames of a tilted screen; `border` adds a black (0 DN, clipped) margin;
    `partly`: a black level of 6 DN and a brightness rising across the image so that the
    brightest steps of about a third of the pixels saturate (255 DN: some steps clipped).
    Camera noise where asked: Gaussian, variance read_dn^2 + (level - black) / gain (DN^2,
    as `NoiseModel`), before the 8-bit rounding (neither: noise-free stacks)."""
    u = np.arange(W, dtype=np.float32)[None, :]
    v = np.arange(H, dtype=np.float32)[:, None]
    x = 0.75 * u + 0.05 * v
    y = 0.5 * v - 0.03 * u + 20.0
    stack = np.empty((len(plan.frames), H, W), dtype=np.uint8)
    black, gain = black_dn(partly), 280.0 * (0.6 + 0.4 * u / W) if partly else 200.0
    shot = 1.0 / gain_e_per_dn if gain_e_per_dn else 0.0
    rng = np.random.default_rng(seed)
    for i, f in enumerate(plan.frames):
        if f.kind == "flat":
            lin = np.full((H, W), f.level, dtype=np.float32)
        else:
            c = x if f.axis == "x" else y
            lin = 0.5 + 0.5 * np.cos(2 * np.pi * c / f.period_px + f.phase_shift)
        level = black + gain * lin
        if read_dn or shot:
            level = level + rng.standard_normal((H, W), dtype=np.float32) * np.sqrt(
                read_dn**2 + shot * (level - black)).astype(np.float32)
            level = np.rint(level)
        stack[i] = np.clip(level, 0.0, 255.0).astype(np.uint8)
        if border:
            stack[i, :, :64] = 0
            stack[i, :, -64:] = 0
    return stack


def timed(fn, repeats: int) -> float:
    """Best wall time of `repeats` runs (seconds)."""
    return timed_cpu(fn, repeats)[0]


def timed_cpu(fn, repeats: int) -> tuple[float, float]:
    """Best wall time of `repeats` runs and the least CPU time of one (seconds)."""
    best, cpu = float("inf"), float("inf")
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return best, cpu


CPU: dict[str, float] = {}  # stage row name -> CPU seconds of its best run
KERNEL_LOAD_S = [float("nan")]  # a fresh process's kernel import + load, wall seconds


def run_numpy(
    plan: Plan, stack: np.ndarray, repeats: int, noise: NoiseModel | float | None
) -> tuple[float, float, float, tuple[float, float, float]]:
    """(setup, add, finish) best wall seconds and the CPU seconds of the best end-to-end run."""
    setup = add = finish = float("inf")
    cpu = (0.0, 0.0, 0.0)
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        dec = StreamingDecoder(plan, (H, W), noise=noise)
        dec.prepare()  # the compiled finish kernel, as a live capture loads it
        c1, t1 = time.process_time(), time.perf_counter()
        for i in range(stack.shape[0]):
            dec.add(i, stack[i])
        c2, t2 = time.process_time(), time.perf_counter()
        dec.finish()
        c3, t3 = time.process_time(), time.perf_counter()
        if t3 - t0 < setup + add + finish:
            cpu = (c1 - c0, c2 - c1, c3 - c2)
        setup, add, finish = min(setup, t1 - t0), min(add, t2 - t1), min(finish, t3 - t2)
    return setup, add, finish, cpu


def run_stack(plan: Plan, stack: np.ndarray, repeats: int, noise: NoiseModel | float | None
              ) -> tuple[float, float]:
    """Best wall seconds and its CPU seconds of `decode_stack` on the whole stack."""
    best, cpu = float("inf"), 0.0
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        decode_stack(plan, stack, noise=noise, prepare=True)
        c1, t1 = time.process_time(), time.perf_counter()
        if t1 - t0 < best:
            best, cpu = t1 - t0, c1 - c0
    return best, cpu


class KernelClock:
    """CPU seconds (each calling thread's own) spent in the accumulation kernel and the
    finish kernel while it is entered: their module attributes wrapped, restored on exit
    (`--breakdown`; the calls are the decoder's, so the maps are unchanged)."""

    TARGETS = ((batch, "accumulate_block", "accumulate"), (kernel_sums, "finish_sums", "finish"))

    def __init__(self) -> None:
        self.cpu = {stage: 0.0 for *_, stage in self.TARGETS}
        self._lock = threading.Lock()
        self._saved: list[tuple] = []

    def __enter__(self) -> KernelClock:
        for module, attr, stage in self.TARGETS:
            fn = getattr(module, attr)
            self._saved.append((module, attr, fn))
            setattr(module, attr, self._timed(fn, stage))
        return self

    def __exit__(self, *exc: object) -> None:
        for module, attr, fn in self._saved:
            setattr(module, attr, fn)
        self._saved.clear()

    def _timed(self, fn, stage: str):
        def call(*args, **kwargs):
            c0 = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                with self._lock:
                    self.cpu[stage] += time.thread_time() - c0
        return call


def breakdown(plan: Plan, stack: np.ndarray, repeats: int, noise: NoiseModel | float | None
              ) -> tuple[float, dict[str, float]]:
    """CPU seconds of `decode_stack` and of its kernels (`KernelClock`), its cheapest run."""
    best: tuple[float, dict[str, float]] = (float("inf"), {})
    for _ in range(repeats):
        with KernelClock() as clock:
            c0 = time.process_time()
            decode_stack(plan, stack, noise=noise, prepare=True)
            total = time.process_time() - c0
        if total < best[0]:
            best = (total, dict(clock.cpu))
    return best


def run_cupy(plan: Plan, stack: np.ndarray, repeats: int) -> list[tuple[str, float]]:
    """Accumulation times on the GPU: frames already on the device, and from pinned host memory."""
    import cupy as cp

    dev = cp.asarray(stack)
    pinned_mem = cp.cuda.alloc_pinned_memory(stack.nbytes)
    pinned = np.frombuffer(pinned_mem, dtype=np.uint8, count=stack.size).reshape(stack.shape)
    pinned[...] = stack

    def on_device() -> None:
        dec = StreamingDecoder(plan, (H, W), noise=1.0, xp=cp)
        for i in range(dev.shape[0]):
            dec.add(i, dev[i])
        cp.cuda.Device().synchronize()

    def from_host() -> None:
        dec = StreamingDecoder(plan, (H, W), noise=1.0, xp=cp)
        for i in range(pinned.shape[0]):
            dec.add(i, cp.asarray(pinned[i]))
        cp.cuda.Device().synchronize()

    on_device()
    return [("cupy add, frames on GPU", timed(on_device, repeats)),
            ("cupy add, from pinned host", timed(from_host, repeats))]


_FRESH = """import sys, time
t0 = time.perf_counter()
from calibration.decode import decode_stack, read_frames
from calibration.shared.plan import read_plan
decode_stack(read_plan(sys.argv[1]), read_frames(sys.argv[2]))
print(time.perf_counter() - t0)
"""


def cli_vs_library(plan: Plan, stack: np.ndarray) -> tuple[float, float, float, str]:
    """Wall seconds of `phasecal decode` (a fresh process: imports, reading, decoding,
    writing the maps), of the library reading + decoding the same .npy in this process, and
    of the library in a fresh process (its imports and kernel loading, no maps written);
    then the command's own stage breakdown (`--timings`) with its CPU seconds."""
    import resource
    import tempfile

    from calibration.decode import read_frames
    from calibration.shared.plan import write_plan

    def children_cpu() -> float:
        r = resource.getrusage(resource.RUSAGE_CHILDREN)
        return r.ru_utime + r.ru_stime

    with tempfile.TemporaryDirectory(prefix="phasecal-decode-") as tmp:
        plan_path, frames_path = Path(tmp) / "plan.json", Path(tmp) / "frames.npy"
        write_plan(plan, plan_path)
        np.save(frames_path, stack)
        c0, t0 = children_cpu(), time.perf_counter()
        run = subprocess.run([sys.executable, "-m", "api.cli", "decode", "--plan",
                              str(plan_path), "--frames", str(frames_path), "-o",
                              str(Path(tmp) / "maps.npz"), "--timings"],
                             check=True, cwd=Path(__file__).resolve().parents[1],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        cli, cli_cpu = time.perf_counter() - t0, children_cpu() - c0
        stages = _stage_breakdown(run.stderr, cli, cli_cpu)
        t0 = time.perf_counter()
        decode_stack(plan, read_frames(frames_path))
        lib = time.perf_counter() - t0
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", _FRESH, str(plan_path), str(frames_path)],
                       check=True, cwd=Path(__file__).resolve().parents[1],
                       stdout=subprocess.DEVNULL)
        return cli, lib, time.perf_counter() - t0, stages


def _stage_breakdown(stderr: str, wall: float, cpu: float) -> str:
    """The `--timings` line as a table; "startup" is the interpreter, the CLI module and its
    parser before the command starts (the process's wall time minus the command's)."""
    line = next((ln for ln in stderr.splitlines() if ln.startswith("timings")), "")
    body = line.partition(":")[2].partition(";")[0].split()
    stages = dict(zip(body[::2], map(float, body[1::2]), strict=True))
    total = stages.pop("total", wall)
    rows = [("startup (interpreter, CLI parser)", wall - total)]
    for name, s in stages.items():
        rows.append((name.replace("read+decode", "read + decode (+ kernel load)"), s))
        if name == "read+decode":  # measured in this (fresh) process: every uint8 variant
            rows.append(("  of which kernel load (about; warm_up)", KERNEL_LOAD_S[0]))
    text = "\n".join(f"  {name:40s} {s:7.3f} s" for name, s in rows)
    return f"{text}\n  {'process wall / CPU (all threads)':40s} {wall:7.3f} s / {cpu:.3f} CPU s"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--xp", default="numpy", choices=["numpy", "cupy"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-cli", action="store_true", help="skip the phasecal decode comparison")
    ap.add_argument("--cli-only", action="store_true",
                    help="only the phasecal decode comparison (about 20 s on an idle machine)")
    ap.add_argument("--breakdown", action="store_true",
                    help="only decode_stack's CPU seconds split into the accumulation "
                         "kernel, the finish kernel and the rest, per configuration")
    ap.add_argument("--read-noise", type=float, default=0.08, metavar="DN",
                    help="camera read noise added to the stacks (std, DN; default 0.08)")
    ap.add_argument("--gain", type=float, default=40.0, metavar="E_PER_DN",
                    help="shot noise added to the stacks: conversion gain, electrons per DN "
                         "(variance = signal above black / gain; default 40; 0: none)")
    args = ap.parse_args()
    plan = bench_plan()
    npf = H * W * len(plan.frames) / 1e6  # Mpixel-frames
    if args.xp == "numpy":  # once per process, before any timing (a service worker's start)
        from calibration.decode.kernel_warm import warm_up

        c0, t0 = time.process_time(), time.perf_counter()
        warm_up()
        print(f"compiled kernels loaded in {time.perf_counter() - t0:.2f} s "
              f"({time.process_time() - c0:.2f} CPU s; once per process, not in the rows)")
        if args.cli_only:
            cli_report(plan, args.repeats, cli_stack(plan, args))
            return 0
        if args.breakdown:
            breakdown_report(plan, args)
            return 0
    rows: list[tuple[str, float]] = []
    finishes: list[tuple[str, float, float]] = []  # (config, finish s, end-to-end s)
    floor = 0.0
    for clip, border, partly in CONFIGS:
        stack = make_stack(plan, border, partly, args.read_noise, args.gain)
        if not (border or partly):
            floor, floor_cpu = timed_cpu(
                lambda s=stack: [s[i].sum(dtype=np.uint64) for i in range(s.shape[0])],
                args.repeats,
            )
            rows.append(("numpy sum over the same bytes (floor)", floor))
            CPU["numpy sum over the same bytes (floor)"] = floor_cpu
        if args.xp == "numpy":
            for noise in (given_noise(args, partly), None):
                tag = f"{clip}, noise {'given' if noise else 'from residuals'}"
                name = f"end to end, whole stack: decode_stack ({tag})"
                t_stack, CPU[name] = run_stack(plan, stack, args.repeats, noise)
                rows.append((name, t_stack))
                t_setup, t_add, t_fin, cpu = run_numpy(plan, stack, args.repeats, noise)
                names = [f"streaming: setup, allocate sums ({tag})",
                         f"streaming: add frame by frame ({tag})",
                         f"streaming: finish ({tag})", f"streaming: end to end ({tag})"]
                rows += list(zip(names, (t_setup, t_add, t_fin, t_setup + t_add + t_fin),
                                 strict=True))
                CPU.update(zip(names, (*cpu, sum(cpu)), strict=True))
                finishes.append((tag, t_fin, t_setup + t_add + t_fin))
        else:
            tag = clip
            rows.extend((f"{name} ({tag})", t) for name, t in run_cupy(plan, stack, args.repeats))
    floor_rate = npf / floor
    noise = (f"camera noise: read {args.read_noise:g} DN, gain {args.gain or 'inf'} e-/DN "
             "(given: that model)" if camera_noise(args) else
             "noise-free stacks (given: 1 DN)")
    print(f"decode benchmark: {W}x{H}, {len(plan.frames)} uint8 frames "
          f"({npf:.0f} Mpixel-frames), xp={args.xp}; {noise}")
    print(f"load: {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} CPUs")
    print(f"{'stage':72s} {'seconds':>9s} {'Mpix-frames/s':>14s} {'vs floor':>9s} "
          f"{'CPU s':>7s}")
    for name, t in rows:
        rate = npf / t
        cpu = f"{CPU[name]:7.3f}" if name in CPU else f"{'':7s}"
        print(f"{name:72s} {t:9.3f} {rate:14.0f} {rate / floor_rate:9.2f} {cpu}")
    whole = [(npf / t, name) for name, t in rows if name.startswith("end to end, whole")]
    if whole:
        print("end to end (decode_stack) against the goal, >= 500 Mpix-frames/s on 2 cores "
              "(the issue's stack: no clipping, noise given):")
        for clip, *_ in CONFIGS:
            rates = [f"{'given' if 'given' in name else 'from residuals'} {r:.0f}"
                     for r, name in whole if f"({clip}," in name]
            print(f"  {clip:16s} {', '.join(rates)}")
        rate, name = min(whole)
        print(f"  worst            {rate:.0f} ({name.split('(')[1].rstrip(')')})")
    if finishes:
        capture = len(plan.frames) / CAPTURE_HZ
        print(f"\nfinish alone ({H * W / 1e6:.1f} Mpixel pose; capture of {len(plan.frames)} "
              f"frames at {CAPTURE_HZ:g} Hz takes {capture:.2f} s)")
        print(f"{'config':44s} {'finish s':>9s} {'Mpixel/s':>9s} {'of decode':>10s} "
              f"{'of capture':>11s}")
        for tag, t_fin, total in finishes:
            print(f"{tag:44s} {t_fin:9.3f} {H * W / 1e6 / t_fin:9.2f} {t_fin / total:10.0%} "
                  f"{t_fin / capture:11.0%}")
    if args.xp == "numpy" and not args.no_cli:
        cli_report(plan, args.repeats, cli_stack(plan, args))
    return 0


def breakdown_report(plan: Plan, args: argparse.Namespace) -> None:
    """`--breakdown`: per configuration, decode_stack's CPU seconds (its cheapest of
    `--repeats` runs) and how much of them the two kernels take."""
    print(f"decode_stack CPU seconds by kernel, {W}x{H}, {len(plan.frames)} uint8 frames, "
          f"best of {args.repeats} (load {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs)")
    print(f"{'stack, noise':40s} {'CPU s':>7s} {'accumulate':>11s} {'finish':>7s} {'rest':>7s}")
    for clip, border, partly in CONFIGS:
        stack = make_stack(plan, border, partly, args.read_noise, args.gain)
        for noise in (given_noise(args, partly), None):
            total, cpu = breakdown(plan, stack, args.repeats, noise)
            rest = total - cpu["accumulate"] - cpu["finish"]
            tag = f"{clip}, {'given' if noise else 'from residuals'}"
            print(f"{tag:40s} {total:7.3f} {cpu['accumulate']:11.3f} {cpu['finish']:7.3f} "
                  f"{rest:7.3f}", flush=True)


def cli_stack(plan: Plan, args: argparse.Namespace) -> np.ndarray:
    """The stack `phasecal decode` is timed on: unclipped, with the camera noise asked."""
    return make_stack(plan, False, False, args.read_noise, args.gain)


def camera_noise(args: argparse.Namespace) -> bool:
    """Whether the stacks carry camera noise."""
    return bool(args.read_noise or args.gain)


def given_noise(args: argparse.Namespace, partly: bool) -> NoiseModel | float:
    """The "noise given" rows' model: the stacks' own camera noise, else 1 DN."""
    if not camera_noise(args):
        return 1.0
    return NoiseModel(read_dn=args.read_noise, gain_e_per_dn=args.gain or None,
                      black_dn=black_dn(partly))


def fresh_kernel_load() -> float:
    """Wall seconds a fresh process spends importing and loading the cached kernels."""
    code = ("import time; t = time.perf_counter(); "
            "from calibration.decode.kernel_warm import warm_up; warm_up(); "
            "print(time.perf_counter() - t)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    return float(out.stdout.split()[-1])


def cli_report(plan: Plan, repeats: int, stack: np.ndarray) -> None:
    """`phasecal decode` against the library on `stack`: best of `repeats` runs of each, the
    stage breakdown of the command's best run, and the ratio (goal: <= 1.5x)."""
    KERNEL_LOAD_S[0] = fresh_kernel_load()
    runs = [cli_vs_library(plan, stack) for _ in range(max(1, repeats))]
    best = min(runs, key=lambda r: r[0])
    cli, lib, fresh = best[0], min(r[1] for r in runs), min(r[2] for r in runs)
    print(f"\nphasecal decode stages, its best of {len(runs)} runs (--timings; load "
          f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs):")
    print(best[3])
    print(f"phasecal decode {cli:.2f} s vs library read + decode {lib:.2f} s "
          f"(noise from residuals): {cli / lib:.2f}x; vs the library in a fresh process "
          f"(imports, kernel load, read, decode; no maps written) {fresh:.2f} s: "
          f"{cli / fresh:.2f}x")


if __name__ == "__main__":
    raise SystemExit(main())
