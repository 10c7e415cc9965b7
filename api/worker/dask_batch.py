"""Batch re-calibration: N sessions x M model settings as one job of independent sub-tasks.

Works on any `Executor` (in-process threads or a Dask cluster): each item becomes one
`run_task` with the sub-job id `<job_id>.<index>`, so on a cluster the items spread over
the workers. The batch reports progress as items finished, forwards a cancel to every
item, and records a failed item (with its reason) without stopping the others.

Manifest (JSON, `"format": "phasecal.batch/1"`; relative paths are relative to the file):

    {"format": "phasecal.batch/1",
     "sessions": [{"name": "rigA", "plan": "rigA/plan.json",
                   "maps": ["rigA/pose0.npz", "rigA/pose1.npz"], "heldout": []}],
     "models": [{"model": "opencv5"}, {"name": "sgcc-fine", "model": "sgcc",
                 "options": {"grid": [24, 16]}}]}
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from api.worker.executor import Executor
from api.worker.tasks import calibrate_task
from calibration.shared.progress import Cancelled, TaskContext

BATCH_FORMAT = "phasecal.batch/1"
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
POLL_S = 0.1


class BatchError(ValueError):
    """A batch manifest or request that does not match `phasecal.batch/1`."""


@dataclass(frozen=True)
class BatchItem:
    """One calibration of the batch: the poses of one session fitted with one model setting."""

    name: str
    plan_path: str
    maps_paths: tuple[str, ...]
    model: str
    out_dir: str
    options: dict[str, Any] = field(default_factory=dict)
    heldout_paths: tuple[str, ...] = ()


def _name(value: Any, where: str) -> str:
    if not isinstance(value, str) or not NAME_RE.match(value):
        raise BatchError(
            f"{where}: expected a name of letters, digits, '_', '.', '-' (at most 64), "
            f"got {value!r}"
        )
    return value


def _paths(value: Any, where: str, base: Path, *, required: bool) -> tuple[str, ...]:
    if value is None and not required:
        return ()
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise BatchError(f"{where}: expected a list of file paths")
    if required and not value:
        raise BatchError(f"{where}: expected at least one file")
    return tuple(str((base / v) if not Path(v).is_absolute() else Path(v)) for v in value)


def items_from_manifest(data: Any, base_dir: str | Path, out_dir: str | Path,
                        source: str = "batch") -> list[BatchItem]:
    """Expand a `phasecal.batch/1` manifest to items `<out_dir>/<session>/<model name>`."""
    base, out = Path(base_dir), Path(out_dir)
    if not isinstance(data, dict) or data.get("format") != BATCH_FORMAT:
        raise BatchError(f"{source}: expected a JSON object with \"format\": \"{BATCH_FORMAT}\"")
    sessions, models = data.get("sessions"), data.get("models")
    if not isinstance(sessions, list) or not sessions:
        raise BatchError(f"{source}: 'sessions' must be a non-empty list")
    if not isinstance(models, list) or not models:
        raise BatchError(f"{source}: 'models' must be a non-empty list")
    parsed_models = []
    for j, m in enumerate(models):
        where = f"{source}: models[{j}]"
        if not isinstance(m, dict) or not isinstance(m.get("model"), str):
            raise BatchError(f"{where}: expected an object with a 'model' name")
        options = m.get("options", {})
        if not isinstance(options, dict):
            raise BatchError(f"{where}.options: expected an object")
        mname = _name(m.get("name", m["model"]), f"{where}.name")
        parsed_models.append((mname, m["model"], options))
    _unique([n for n, _, _ in parsed_models], f"{source}: models")
    items = []
    names = []
    for i, ses in enumerate(sessions):
        where = f"{source}: sessions[{i}]"
        if not isinstance(ses, dict):
            raise BatchError(f"{where}: expected an object with 'name', 'plan' and 'maps'")
        sname = _name(ses.get("name"), f"{where}.name")
        names.append(sname)
        plan = ses.get("plan")
        if not isinstance(plan, str) or not plan:
            raise BatchError(f"{where}.plan: expected the path of the session's plan.json")
        plan_path = str(base / plan) if not Path(plan).is_absolute() else plan
        maps = _paths(ses.get("maps"), f"{where}.maps", base, required=True)
        heldout = _paths(ses.get("heldout"), f"{where}.heldout", base, required=False)
        for mname, model, options in parsed_models:
            items.append(BatchItem(f"{sname}/{mname}", plan_path, maps, model,
                                   str(out / sname / mname), dict(options), heldout))
    _unique(names, f"{source}: sessions")
    return items


def _unique(names: list[str], where: str) -> None:
    seen = set()
    for n in names:
        if n in seen:
            raise BatchError(f"{where}: name {n!r} appears twice; names become output folders")
        seen.add(n)


def read_manifest(path: str | Path, out_dir: str | Path) -> list[BatchItem]:
    """Read and expand a batch manifest file (relative paths resolve against its folder)."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise BatchError(f"{p}: not valid JSON ({exc})") from exc
    return items_from_manifest(data, p.parent, out_dir, source=str(p))


def _default_task() -> Callable[..., dict[str, Any]]:
    return calibrate_task


def run_batch(
    executor: Executor,
    items: Sequence[BatchItem],
    ctx: TaskContext,
    task_fn: Callable[..., dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """Run every item as a sub-task of job `ctx.job_id`; a JSON-able summary per item.

    `task_fn(ctx, plan_path, maps_paths, model, out_dir, options=..., heldout_paths=...)`
    defaults to `api.worker.tasks.calibrate_task`. Raises `Cancelled` when the
    batch was cancelled (after every running item stopped).
    """
    if not items:
        raise BatchError("batch: no items to run")
    fn = task_fn or _default_task()
    t0 = time.perf_counter()
    total = len(items)
    ctx.progress(0, total, "batch")
    pending: dict[Future, int] = {}
    sub_ids = [f"{ctx.job_id}.{i}" for i in range(total)]
    for i, item in enumerate(items):
        Path(item.out_dir).mkdir(parents=True, exist_ok=True)
        fut = executor.run_task(
            fn, item.plan_path, list(item.maps_paths), item.model, item.out_dir,
            job_id=sub_ids[i], options=dict(item.options),
            heldout_paths=list(item.heldout_paths) or None,
        )
        pending[fut] = i
    outcomes: list[dict[str, Any] | None] = [None] * total
    cancel_sent = False
    while pending:
        done, _ = wait(list(pending), timeout=POLL_S, return_when=FIRST_COMPLETED)
        for fut in done:
            i = pending.pop(fut)
            outcomes[i] = _outcome(items[i], fut)
        if done:
            ctx.progress(total - len(pending), total, "batch")
        if not cancel_sent and ctx.cancelled():
            cancel_sent = True
            for i in pending.values():
                executor.cancel(sub_ids[i])
    if cancel_sent:
        raise Cancelled(f"batch {ctx.job_id} was cancelled")
    results = [o for o in outcomes if o is not None]
    return {
        "items": results,
        "succeeded": sum(r["status"] == "succeeded" for r in results),
        "failed": sum(r["status"] == "failed" for r in results),
        "wall_s": round(time.perf_counter() - t0, 3),
    }


def _outcome(item: BatchItem, fut: Future) -> dict[str, Any]:
    """The summary of one finished item: its result, or why it failed or stopped."""
    base = {"name": item.name, "model": item.model, "out_dir": item.out_dir}
    exc = fut.exception()
    if exc is None:
        return {**base, "status": "succeeded", "result": fut.result()}
    status = "cancelled" if isinstance(exc, Cancelled) else "failed"
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return {**base, "status": status, "error": f"{type(exc).__name__}: {msg}" if msg else
            type(exc).__name__}


__all__ = [
    "BATCH_FORMAT",
    "BatchError",
    "BatchItem",
    "items_from_manifest",
    "read_manifest",
    "run_batch",
]
