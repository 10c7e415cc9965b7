"""Scale-out benchmark: a batch of calibrations in-process vs on a Dask LocalCluster.

Prints throughput of each executor, their ratio, and the scheduler overhead per task
(no-op job tasks through `DaskExecutor.run_task`, sequential round trip and pipelined).

    .venv/bin/python benchmarks/scaleout.py [--items 8] [--workers 2] [--task auto]

`--task fit` runs phasecal's fit (`calibration.fit.dispatch.calibrate`, model `--model`)
on the stored maps and writes model.json; `--task service` runs the service's whole
`api.worker.tasks.calibrate_task` (fit + exports); `--task opencv` runs a
self-contained OpenCV pinhole calibration; `auto` picks fit when it is importable.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

# Dask's nanny starts workers with one BLAS/OpenMP thread; do the same here so both sides
# run the same floating-point code paths (results then match bit for bit) and compete fairly.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from acquisition.patterns import build_plan  # noqa: E402
from api.worker.dask_batch import BATCH_FORMAT, items_from_manifest, run_batch  # noqa: E402
from api.worker.dask_executor import DaskExecutor, start_local_cluster  # noqa: E402
from api.worker.executor import InProcessExecutor  # noqa: E402
from calibration.shared.maps import save_maps  # noqa: E402
from calibration.shared.plan import write_plan  # noqa: E402
from calibration.shared.progress import TaskContext  # noqa: E402


def opencv_calibrate_task(ctx: TaskContext, plan_path: str, maps_paths: list[str], model: str,
                          out_dir: str, *, options: dict[str, Any],
                          heldout_paths: list[str] | None = None) -> dict[str, Any]:
    """Pinhole + 5 distortion coefficients with cv2.calibrateCamera from stored maps."""
    import cv2

    from calibration.shared.maps import load_maps
    from calibration.shared.plan import read_plan

    cv2.setNumThreads(1)
    plan = read_plan(plan_path)
    pitch = np.asarray(plan.screen.pitch_mm, np.float64)
    step = int(options.get("subsample", 8))
    obj, img = [], []
    for i, p in enumerate(maps_paths):
        ctx.check_cancelled()
        pixels, screen, _ = load_maps(p).correspondences()
        keep = slice(None, None, step)
        pts = np.column_stack([screen[keep] * pitch, np.zeros(len(screen[keep]))])
        obj.append(pts.astype(np.float32))
        img.append(pixels[keep].astype(np.float32))
        ctx.progress(i + 1, len(maps_paths), "load")
    h, w = load_maps(maps_paths[0]).shape
    f0 = float(max(w, h))
    k0 = np.array([[f0, 0, (w - 1) / 2], [0, f0, (h - 1) / 2], [0, 0, 1]])
    rms, k, dist, _, _ = cv2.calibrateCamera(obj, img, (w, h), k0, None,
                                             flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    np.savez(Path(out_dir) / "opencv_result.tmp.npz", K=k, dist=dist)
    os.replace(Path(out_dir) / "opencv_result.tmp.npz", Path(out_dir) / "opencv_result.npz")
    return {"rms_px": float(rms), "fx": float(k[0, 0])}


def fit_task(ctx: TaskContext, plan_path: str, maps_paths: list[str], model: str,
             out_dir: str, *, options: dict[str, Any],
             heldout_paths: list[str] | None = None) -> dict[str, Any]:
    """phasecal's own fit of `model` to the stored maps; model.json written atomically."""
    from calibration.fit.dispatch import calibrate
    from calibration.models.base import save_model
    from calibration.shared.maps import load_maps
    from calibration.shared.plan import read_plan

    maps = [load_maps(p) for p in maps_paths]
    result = calibrate(maps, read_plan(plan_path).screen, model, options=options,
                       progress=ctx.progress, cancelled=ctx.cancelled)
    save_model(result.model, Path(out_dir) / "model.json")
    return {"rms_px": float(result.stats.get("rms_px", float("nan")))}


def make_sessions(root: Path, n_sessions: int, n_poses: int, seed: int) -> dict[str, Any]:
    """Stored plans and synthetic maps (hw_mocks ground truth) for `n_sessions` sessions."""
    from hw_mocks.cameras import mild_pinhole
    from hw_mocks.poses import random_poses
    from hw_mocks.synthetic import synthetic_maps

    rng = np.random.default_rng(seed)
    plan = build_plan(1920, 1080, 0.2745)
    camera = mild_pinhole(640, 480)
    sessions = []
    for s in range(n_sessions):
        d = root / f"s{s}"
        d.mkdir(parents=True)
        write_plan(plan, d / "plan.json")
        maps = []
        for k, pose in enumerate(random_poses(camera, plan.screen, n_poses, rng)):
            m, _ = synthetic_maps(camera, pose, plan.screen, sigma_px=0.05, rng=rng)
            save_maps(m, d / f"pose{k}.npz")
            maps.append(f"s{s}/pose{k}.npz")
        sessions.append({"name": f"s{s}", "plan": f"s{s}/plan.json", "maps": maps})
    return {"format": BATCH_FORMAT, "sessions": sessions}


def noop_task(ctx: TaskContext, i: int) -> int:
    """Does nothing but the job protocol (start event, one cancel poll, one progress)."""
    ctx.check_cancelled()
    ctx.progress(1, 1, "noop")
    return i


def _outputs(out_dir: Path, item: dict[str, Any]) -> dict[str, Any]:
    """What an item produced: its summary and, where written, its model.json."""
    model = out_dir / "model.json"
    return {"result": item.get("result"),
            "model": json.loads(model.read_text()) if model.exists() else None}


def max_rel_diff(a: Any, b: Any) -> float:
    """Largest relative difference between the numbers of two JSON-like trees (inf if the
    trees differ in shape or in non-numbers)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return float("inf")
        return max((max_rel_diff(a[k], b[k]) for k in a), default=0.0)
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return float("inf")
        return max((max_rel_diff(x, y) for x, y in zip(a, b, strict=True)), default=0.0)
    if isinstance(a, int | float) and isinstance(b, int | float) and not isinstance(a, bool):
        if a == b or (math.isnan(a) and math.isnan(b)):
            return 0.0
        return abs(a - b) / max(abs(a), abs(b))
    return 0.0 if a == b else float("inf")


def timed_batch(executor: Any, items: list, task: Any, job: str, warm: int) -> tuple[float, dict]:
    """Wall time and summary of one batch run, after `warm` untimed items (imports, caches)."""
    run_batch(executor, items[:warm], TaskContext(job + "-warm"), task_fn=task)
    t0 = time.perf_counter()
    summary = run_batch(executor, items, TaskContext(job), task_fn=task)
    return time.perf_counter() - t0, summary


def overhead(ex: DaskExecutor, n_seq: int, n_par: int) -> tuple[float, float]:
    """Mean sequential round trip and pipelined wall per task of no-op job tasks (seconds)."""
    ex.run_task(noop_task, -1, job_id="warm").result()
    seq = []
    for i in range(n_seq):
        t0 = time.perf_counter()
        ex.run_task(noop_task, i, job_id=f"seq{i}").result()
        seq.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    futs = [ex.run_task(noop_task, i, job_id=f"par{i}") for i in range(n_par)]
    for f in futs:
        f.result()
    return statistics.mean(seq), (time.perf_counter() - t0) / n_par


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--items", type=int, default=8, help="calibrations in the batch")
    ap.add_argument("--poses", type=int, default=5, help="poses per session")
    ap.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes")
    ap.add_argument("--task", choices=["auto", "fit", "service", "opencv"], default="auto")
    ap.add_argument("--model", default="opencv5", help="model for --task fit/service")
    ap.add_argument("--noop-tasks", type=int, default=200, help="tasks for the overhead test")
    args = ap.parse_args(argv)

    kind = args.task
    if kind == "auto":
        kind = "fit" if importlib.util.find_spec("calibration.fit.dispatch") else "opencv"
    if kind == "service":
        from api.worker.tasks import calibrate_task as task
    else:
        task = fit_task if kind == "fit" else opencv_calibrate_task
    model = "opencv-pinhole5" if kind == "opencv" else args.model
    with tempfile.TemporaryDirectory(prefix="phasecal-scaleout-") as tmp:
        root = Path(tmp)
        manifest = make_sessions(root / "data", args.items, args.poses, seed=1)
        manifest["models"] = [{"model": model}]
        items_in = items_from_manifest(manifest, root / "data", root / "inproc")
        items_dask = items_from_manifest(manifest, root / "data", root / "dask")

        rows = []
        for threads in (1, args.workers):
            ex = InProcessExecutor(max_workers=threads)
            wall, summary = timed_batch(ex, items_in, task, f"b-in{threads}", threads)
            ex.shutdown()
            rows.append((f"in-process, {threads} thread(s)", wall, summary))
        cluster = start_local_cluster(args.workers)
        try:
            dex = DaskExecutor(cluster.scheduler_address)
            wall, summary = timed_batch(dex, items_dask, task, "b-dask", args.workers)
            rows.append((f"LocalCluster, {args.workers} procs x 1 thread", wall, summary))
            seq_s, par_s = overhead(dex, 50, args.noop_tasks)
            dex.shutdown()
        finally:
            cluster.close()
        diff = max(
            max_rel_diff(_outputs(Path(a["out_dir"]), a), _outputs(Path(b["out_dir"]), b))
            for a, b in zip(rows[0][2]["items"], rows[-1][2]["items"], strict=True))

    task_name = f"{kind} task, model {model}"
    print(f"scale-out: {args.items} calibrations ({task_name}, {args.poses} poses of 640x480), "
          f"{os.cpu_count()} CPUs")
    print(f"{'executor':36s} {'wall s':>8s} {'items/s':>8s} {'vs 1 thread':>11s} {'ok':>4s}")
    base = rows[0][1]
    for label, wall, summary in rows:
        print(f"{label:36s} {wall:8.2f} {args.items / wall:8.2f} {base / wall:10.2f}x "
              f"{summary['succeeded']:4d}")
    print(f"LocalCluster vs in-process 1 thread: {base / rows[-1][1]:.2f}x; "
          f"max relative difference of results and model.json numbers: {diff:.3g}")
    print(f"scheduler overhead per task (no-op run_task): sequential round trip "
          f"{seq_s * 1e3:.1f} ms, pipelined {par_s * 1e3:.1f} ms over {args.noop_tasks} tasks "
          f"(goal < 50 ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
