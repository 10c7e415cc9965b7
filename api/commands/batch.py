"""`phasecal batch`: re-calibrate many sessions and/or model settings as one job.

Items run on the in-process executor, on a Dask scheduler (`--executor tcp://host:8786`
or env PHASECAL_DASK) or on a private local cluster (`--executor local:N`). Each item
writes `<output>/<session>/<model name>/` (model.json, result.json, exports); the batch
summary goes to `<output>/batch.json`.
"""

from __future__ import annotations

import argparse
import secrets
import sys
from pathlib import Path

from api.cli import UserError
from api.worker import make_executor
from api.worker.dask_batch import (
    BATCH_FORMAT,
    items_from_manifest,
    read_manifest,
    run_batch,
)
from calibration import model_spec
from calibration.shared.atomic import write_json_atomic
from calibration.shared.progress import TaskContext


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--manifest", help="phasecal.batch/1 JSON listing sessions and models")
    p.add_argument("--plan", help="plan.json of a single session (instead of --manifest)")
    p.add_argument("--maps", nargs="+", metavar="MAPS", help="maps NPZ files of that session")
    p.add_argument("--heldout", nargs="+", default=[], metavar="MAPS",
                   help="held-out maps NPZ files of that session")
    p.add_argument("--model", nargs="+", metavar="NAME",
                   help="model names to fit to that session, one item each")
    p.add_argument("--session-name", default="session",
                   help="output folder name of that session (default: session)")
    p.add_argument("--executor", default=None, metavar="ADDRESS",
                   help="tcp://host:port of a Dask scheduler, local:N for a private "
                        "N-worker cluster, or inprocess (default: env PHASECAL_DASK, else "
                        "in-process)")
    p.add_argument("-o", "--output", required=True, help="output folder")


def _items(args: argparse.Namespace) -> list:
    single = [args.plan, args.maps, args.model]
    if args.manifest:
        if any(v for v in single):
            raise UserError("give either --manifest or --plan/--maps/--model, not both")
        return read_manifest(args.manifest, args.output)
    if not all(single):
        raise UserError("give --manifest, or all of --plan, --maps and --model")
    manifest = {
        "format": BATCH_FORMAT,
        "sessions": [{"name": args.session_name, "plan": args.plan, "maps": args.maps,
                      "heldout": args.heldout}],
        "models": [{"model": m} for m in args.model],
    }
    return items_from_manifest(manifest, Path.cwd(), args.output, source="command line")


def _missing_inputs(items: list) -> str | None:
    """The first input file that does not exist, if any (checked before any work starts)."""
    for item in items:
        for path in (item.plan_path, *item.maps_paths, *item.heldout_paths):
            if not Path(path).is_file():
                return f"{item.name}: input file {path} does not exist"
    return None


def _invalid_item(items: list) -> str | None:
    """The first item whose model or options the model registry refuses (before any work)."""
    for item in items:
        try:
            model_spec(item.model).parse_options(item.options)
        except ValueError as exc:
            return f"{item.name}: {exc}"
    return None


def run(args: argparse.Namespace) -> int:
    items = _items(args)
    problem = _missing_inputs(items) or _invalid_item(items)
    if problem:
        raise UserError(problem)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    executor = make_executor(args.executor)
    job_id = f"batch-{secrets.token_hex(6)}"

    def report(done: int, total: int, stage: str) -> None:
        print(f"{stage}: {done}/{total} items finished", file=sys.stderr)

    try:
        summary = run_batch(executor, items, TaskContext(job_id, report))
    except KeyboardInterrupt:
        for i in range(len(items)):
            executor.cancel(f"{job_id}.{i}")
        executor.shutdown(wait=False)
        raise
    executor.shutdown()
    write_json_atomic(out / "batch.json", {"job_id": job_id, **summary})
    for r in summary["items"]:
        detail = r.get("error") or f"-> {r['out_dir']}"
        print(f"{r['status']:9s} {r['name']} {detail}")
    print(f"wrote {out / 'batch.json'}: {summary['succeeded']} succeeded, "
          f"{summary['failed']} failed in {summary['wall_s']:.1f} s")
    if summary["failed"]:
        raise UserError(f"{summary['failed']} of {len(items)} items failed "
                        f"(reasons in {out / 'batch.json'})")
    return 0
