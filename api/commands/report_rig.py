"""`phasecal report` of a rig model (phasecal.rig/1): the page the service draws for a rig
calibration (every camera, the extrinsics with their 1-sigma, a verdict, held-out views),
drawn from the rig file, each camera's `CAMERA/VIEW=PATH` maps or observation files and the
fit's statistics. `report` hands over here when --model is a rig."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from api.cli import UserError
from api.commands.calibrate_rig import rig_requested, rig_result_path, split_prefix
from api.version import phasecal_version
from calibration import (
    ReportHeader,
    RigModel,
    RigReportInputs,
    draw_rig_report,
    rig_model_stats,
    write_rig_downloads,
)


def rig_inputs(args: argparse.Namespace, rig: RigModel, model: str
               ) -> list[tuple[str, str, str, str]]:
    """(camera, view, "maps" | "observations", path) of every input file; a one-line error
    for plain paths, a camera the rig lacks, a rig camera without files, a file given twice
    or missing, or maps and observations together."""
    if not rig_requested(args):
        raise UserError(f"--maps/--observations: {model} is a rig (phasecal.rig/1); name each "
                        "file CAMERA/VIEW=PATH as `phasecal calibrate` takes them")
    entries, seen = [], set()
    for kind, flag, paths in (("maps", "--maps", args.maps or []),
                              ("observations", "--observations", args.observations or [])):
        for text in paths:
            camera, view, path = split_prefix(text)  # type: ignore[misc]  # rig_requested held
            if camera not in rig.cameras:
                raise UserError(f"{flag}: camera {camera!r} is not in the rig {model} (its "
                                f"cameras: {sorted(rig.cameras)})")
            if (camera, view) in seen:
                raise UserError(f"{flag}: {camera}/{view} is given twice")
            if not Path(path).is_file():
                raise UserError(f"{flag}: file not found: {path}")
            seen.add((camera, view))
            entries.append((camera, view, kind, path))
    if len({e[2] for e in entries}) > 1:
        raise UserError("inputs: a rig report counts each camera's coverage from maps or from "
                        "observations; give one kind")
    missing = [c for c in rig.cameras if all(e[0] != c for e in entries)]
    if missing:
        raise UserError(f"inputs: no CAMERA/VIEW= files for camera(s) {missing} of the rig "
                        f"{model}; the report covers every camera")
    return entries


def fit_statistics(rig: RigModel, model: Path, result: str | None) -> tuple[str | None,
                                                                            dict[str, Any]]:
    """The fit's statistics file (given, else the one `phasecal calibrate` wrote beside the
    rig; None without one: the statistics the rig model carries) and its statistics; a
    one-line error for a file that is not this rig's fit."""
    path = result or (str(rig_result_path(model)) if rig_result_path(model).is_file() else None)
    if path is None:
        return None, rig_model_stats(rig)
    try:
        stats = json.loads(Path(path).read_text(encoding="utf-8")).get("stats")
    except FileNotFoundError:
        raise UserError(f"--result: file not found: {path}") from None
    except (UnicodeDecodeError, json.JSONDecodeError, AttributeError) as exc:
        raise UserError(f"--result: {path} is not a fit's result JSON ({exc})") from None
    if not isinstance(stats, dict):
        raise UserError(f"--result: {path} has no \"stats\" object")
    fitted, kept = stats.get("reduced_chi2"), rig.stats.get("reduced_chi2")
    if stats.get("reference") != rig.reference or (
            fitted is not None and kept is not None and fitted != kept):
        raise UserError(f"--result: {path} is not the fit of {model} (reference "
                        f"{stats.get('reference')!r}, reduced chi2 {fitted}; the rig: "
                        f"{rig.reference!r}, {kept})")
    return path, stats


def split_views(entries: list[tuple[str, str, str, str]], stats: dict[str, Any],
                heldout: list[str]) -> list[str]:
    """The training views in input order, after checking each input view against the fit:
    a training view of it, or a view it held out and scored (named with --heldout-view)."""
    trained = {row.get("view") for row in stats.get("per_view", [])}
    if not trained:
        raise UserError("--result: the fit's statistics name no fitted view (per_view); give "
                        "the result.json of the fit that wrote this rig")
    scored = {row.get("view") for row in stats.get("heldout") or []}
    views = list(dict.fromkeys(e[1] for e in entries))
    for view in heldout:
        if view not in views:
            raise UserError(f"--heldout-view: no input file of view {view!r}; views: {views}")
        if view in trained:
            raise UserError(f"--heldout-view: the fit used view {view!r}; it was not held out")
        if view not in scored:
            raise UserError(f"--heldout-view: the fit's statistics hold no score of view "
                            f"{view!r} (a view held out with `phasecal calibrate "
                            "--heldout-view`, whose RIG.result.json lies beside the rig or is "
                            "given with --result)")
    for view in views:
        if view in scored and view not in heldout:
            raise UserError(f"inputs: the fit held out view {view!r}; name it with "
                            f"--heldout-view {view}")
        if view not in trained and view not in scored:
            raise UserError(f"inputs: view {view!r} is not one of the fit's (fitted: "
                            f"{sorted(trained)}, held out: {sorted(scored)})")
    return [v for v in views if v not in heldout]


def draw_rig_report_files(args: argparse.Namespace, rig: RigModel) -> tuple[Path, str]:
    """Draw the rig's report (the page, its coverage PNGs, the rig model and its exports)
    into --output; the page's path and what it was drawn from, in words."""
    model_path = Path(args.model)
    if args.heldout_maps:
        raise UserError("--heldout-maps: a rig's held-out views are CAMERA/VIEW= inputs "
                        "named with --heldout-view VIEW")
    entries = rig_inputs(args, rig, args.model)
    result, stats = fit_statistics(rig, model_path, args.result)
    training = split_views(entries, stats, args.heldout_view)
    files: dict[str, list[str]] = {}
    for camera, view, _, path in entries:
        if view in training:
            files.setdefault(camera, []).append(path)
    observed = entries[0][2] == "observations"
    header = ReportHeader(
        title=args.title or f"Rig calibration report: {model_path.name}",
        session=args.session, rig=args.rig,
        cameras=(args.cameras if args.cameras != "not given" else ", ".join(
            f"{name} ({cam.model.type_name})" for name, cam in rig.cameras.items())),
        date="model written " + time.strftime("%Y-%m-%d %H:%M UTC",
                                              time.gmtime(model_path.stat().st_mtime)),
        software=f"phasecal {phasecal_version()}", poses_used=training,
        heldout=list(args.heldout_view))
    out = Path(args.output)
    downloads = write_rig_downloads(rig, model_path, out)
    inputs = RigReportInputs(str(model_path), result, {} if observed else files, header,
                             downloads, observations=files if observed else {})
    page_path = Path(draw_rig_report(inputs, str(out)))
    written = sum(d.href is not None for d in downloads)
    source = result or "the statistics the rig model carries"
    return page_path, (f"{len(rig.cameras)} cameras, {len(training)} views, statistics from "
                       f"{source}, {written} downloads")
