"""`phasecal decode` against the `fringes` package's command line on the same stack, one-shot.

Run: .venv/bin/python benchmarks/cli_decode.py [--sizes 640x480,1280x1024] [--repeats 5]

A lab script decodes each pose with one command, so both decoders are timed as fresh
processes: interpreter start, imports, loading their compiled (numba, cached) kernels,
reading the stack from the page cache, decoding, writing the result. The peer is `fringes`
(PyPI, by C. Kludt), a phase-shift encoder/decoder with its own numba kernels. Its metadata
says GPL-3.0-only: it is never a dependency of phasecal. This benchmark installs it with
pip into its own virtual environment under benchmarks/.cache/ (git-ignored) and only runs
its command line there, as a separate program.

The stack: a camera seeing a screen of its own size at a slight tilt, two flats (bright,
dark) then 3 periods x 10 steps per axis (62 uint8 frames), camera noise as the decode
benchmark's default (read 0.08 DN, 40 e-/DN). phasecal reads it with its plan; `fringes`
has no flats, so it reads the same 60 fringe frames without them, written as their own
`.npy` (both read `.npy`), with the same periods (its wavelengths `l`), steps and phase
convention (`reverse`, `p0` 0) in a config file its own `Fringes.save` writes. phasecal
estimates its noise from the residuals (the command's default). Each run's maps are
compared with the screen coordinates the stack was drawn from (median |error| of the x
coordinate over the pixels each calls valid), so both are seen decoding the stack.

Each size: one untimed run of each first (fringes compiles its kernels on its first run
after install, phasecal's are compiled by `make setup`), then `--repeats` runs of each,
interleaved; the medians of wall and CPU seconds (the child's user + system, all
threads), and phasecal's over fringes'. On a shared, loaded machine wall times swing with
the other work; CPU seconds much less: the CPU ratio decides there, the wall ratio on an
idle machine. The 1-minute load is printed with each table.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from acquisition.patterns import build_plan, choose_periods
from calibration.shared.maps import load_maps
from calibration.shared.plan import Plan, write_plan

ROOT = Path(__file__).resolve().parents[1]

FRINGES = "fringes==2.1.0"  # the release measured; pinned so that reruns compare alike
CACHE = ROOT / "benchmarks" / ".cache"
STEPS = 10
BLACK_DN, GAIN_DN = 20.0, 200.0  # black level, bright-minus-black (no step clips)
READ_DN, E_PER_DN = 0.08, 40.0  # camera noise as benchmarks/decode.py's default


def fringes_python() -> Path:
    """The interpreter of the benchmark's own `fringes` environment, made on first use."""
    venv = CACHE / "fringes-venv"
    python = venv / "bin" / "python"
    if not python.exists():
        print(f"installing {FRINGES} into {venv.relative_to(ROOT)} (first run only)",
              flush=True)
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        subprocess.run([str(python), "-m", "pip", "install", "-q", FRINGES], check=True)
    return python


def screen_coordinates(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Screen x, y (px) each camera pixel sees: a slight tilt, inside the screen."""
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    return 0.96 * u + 0.02 * v + 4.0, 0.96 * v - 0.02 * u + 0.02 * w + 4.0


def make_plan(h: int, w: int) -> Plan:
    """Flats, then 3 periods x `STEPS` steps per axis; both axes the same periods (the
    coarsest covers the wider side), as `fringes` takes one wavelength list per set."""
    periods = choose_periods(max(w, h), 8.0 * max(w, h) / 160.0, 8.0)
    return build_plan(w, h, 0.25, steps=STEPS, periods_x=periods, periods_y=periods)


def make_stack(plan: Plan, h: int, w: int, seed: int = 0) -> np.ndarray:
    """The camera's uint8 frames of `plan` (noise as in the module docstring)."""
    xs, ys = screen_coordinates(h, w)
    rng = np.random.default_rng(seed)
    stack = np.empty((len(plan.frames), h, w), dtype=np.uint8)
    for i, f in enumerate(plan.frames):
        if f.kind == "flat":
            lin = np.full((h, w), f.level)
        else:
            c = xs if f.axis == "x" else ys
            lin = f.offset + f.amplitude * np.cos(2 * np.pi * c / f.period_px + f.phase_shift)
        level = BLACK_DN + GAIN_DN * lin
        level += rng.standard_normal((h, w)) * np.sqrt(READ_DN**2 + (level - BLACK_DN) / E_PER_DN)
        stack[i] = np.clip(np.rint(level), 0, 255).astype(np.uint8)
    return stack


def fringes_config(python: Path, plan: Plan, h: int, w: int, path: Path) -> None:
    """`fringes`' config for the plan's fringe frames, written by its own `Fringes.save`."""
    periods = [s.period_px for s in plan.period_sets("x")]
    code = ("import sys, json, fringes; a = json.loads(sys.argv[1]); "
            "fringes.Fringes(X=a['w'], Y=a['h'], K=len(a['l']), N=a['n'], "
            "reverse=True, p0=0.0).save(a['path']); "
            "f = fringes.Fringes(); f.load(a['path']); f.l = a['l']; f.save(a['path'])")
    args = json.dumps({"w": w, "h": h, "l": periods, "n": STEPS, "path": str(path)})
    subprocess.run([str(python), "-c", code, args], check=True, capture_output=True)


def timed(cmd: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds (user + system of the child, all its threads) of one run."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def errors(tmp: Path, h: int, w: int) -> tuple[float, float, float, float]:
    """Median |x error| (screen px) and valid fraction of phasecal's and fringes' maps."""
    xs, _ = screen_coordinates(h, w)
    maps = load_maps(tmp / "maps.npz")
    ours = float(np.median(np.abs(maps.x[maps.mask] - xs[maps.mask])))
    with np.load(tmp / "fringes.npz") as out:
        theirs_x = out["x"][0, ..., 0]  # (direction, Y, X, colour): direction 0 is x
    ok = np.isfinite(theirs_x)
    theirs = float(np.median(np.abs(theirs_x[ok] - xs[ok])))
    return ours, float(maps.mask.mean()), theirs, float(ok.mean())


def run_size(python: Path, h: int, w: int, repeats: int) -> dict[str, float]:
    """Medians of both commands on one stack size (see the module docstring)."""
    plan = make_plan(h, w)
    with tempfile.TemporaryDirectory(prefix="phasecal-cli-decode-") as name:
        tmp = Path(name)
        write_plan(plan, tmp / "plan.json")
        stack = make_stack(plan, h, w)
        flats = len(plan.flat_indices(1.0)) + len(plan.flat_indices(0.0))
        if any(f.kind == "flat" for f in plan.frames[flats:]):
            raise SystemExit("the plan's flats are expected first")
        np.save(tmp / "frames.npy", stack)
        np.save(tmp / "fringes_frames.npy", stack[flats:])
        fringes_config(python, plan, h, w, tmp / "fringes.yaml")
        ours = [sys.executable, "-m", "api.cli", "decode", "--plan", str(tmp / "plan.json"),
                "--frames", str(tmp / "frames.npy"), "-o", str(tmp / "maps.npz")]
        theirs = [str(python), "-m", "fringes", "-i", str(tmp / "fringes_frames.npy"),
                  "--config", str(tmp / "fringes.yaml"), str(tmp / "fringes.npz")]
        timed(ours), timed(theirs)  # untimed first runs (compiles, page cache)
        runs: dict[str, list[tuple[float, float]]] = {"phasecal": [], "fringes": []}
        for _ in range(repeats):
            runs["phasecal"].append(timed(ours))
            runs["fringes"].append(timed(theirs))
        err = errors(tmp, h, w)
    out = {f"{who} {what}": statistics.median(r[k] for r in rs)
           for who, rs in runs.items() for k, what in ((0, "wall"), (1, "cpu"))}
    out.update(frames=len(plan.frames), fringes_frames=len(plan.frames) - flats,
               our_err=err[0], our_valid=err[1], their_err=err[2], their_valid=err[3])
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="640x480,1280x1024", help="WxH list (default %(default)s)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    python = fringes_python()
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    rows = []
    for w, h in sizes:
        r = run_size(python, h, w, max(1, args.repeats))
        rows.append((w, h, r))
    print(f"phasecal decode vs {FRINGES} (its own venv), medians of {args.repeats} runs each; "
          f"load {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} CPUs")
    print(f"{'stack':22s} {'phasecal wall':>13s} {'fringes wall':>12s} {'ratio':>6s} "
          f"{'phasecal CPU':>12s} {'fringes CPU':>11s} {'ratio':>6s}   x error (valid): "
          "phasecal, fringes")
    for w, h, r in rows:
        stack = f"{w}x{h}, {r['frames']:.0f}/{r['fringes_frames']:.0f} fr"
        print(f"{stack:22s} {r['phasecal wall']:13.3f} {r['fringes wall']:12.3f} "
              f"{r['phasecal wall'] / r['fringes wall']:6.2f} {r['phasecal cpu']:12.3f} "
              f"{r['fringes cpu']:11.3f} {r['phasecal cpu'] / r['fringes cpu']:6.2f}   "
              f"{r['our_err']:.3f} px ({r['our_valid']:.1%}), "
              f"{r['their_err']:.3f} px ({r['their_valid']:.1%})")
    print("goal: phasecal wall <= 0.8x fringes' (CPU ratio where the machine is loaded)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
