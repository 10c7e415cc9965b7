"""`phasecal report`: the calibration report (HTML page + PNGs, the model and its exports
beside it) from a model and its maps, or from a rig model and its cameras' `CAMERA/VIEW=`
maps or observations (`api.commands.report_rig`)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from api.cli import UserError
from api.commands.calibrate_rig import rig_requested
from api.commands.report_rig import draw_rig_report_files
from api.version import phasecal_version
from calibration import (
    ReportHeader,
    ReportInputs,
    RigModel,
    draw_report,
    is_rig_document,
    load_model,
    rig_from_dict,
    self_contained,
    write_downloads,
)

SINGLE_FILE = "report-single.html"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True,
                   help="fitted model (phasecal.model/1 JSON) or rig model (phasecal.rig/1)")
    p.add_argument("--plan", help="pattern plan (for the screen geometry); a single camera's "
                                  "report needs it, a rig's does not")
    p.add_argument("--maps", nargs="+", metavar="[CAMERA/VIEW=]PATH",
                   help="training poses' maps (.npz); a rig's as CAMERA/VIEW=PATH, held-out "
                        "views included")
    p.add_argument("--observations", nargs="+", metavar="CAMERA/VIEW=PATH",
                   help="rig fitted to board observations: each camera's observation files")
    p.add_argument("--heldout-maps", nargs="+", default=[], metavar="NPZ",
                   help="held-out poses' maps, validated with the model (one camera)")
    p.add_argument("--heldout-view", action="append", default=[], metavar="VIEW",
                   help="rig: a view the fit held out (its files are among the inputs; "
                        "repeatable)")
    p.add_argument("--result", help="the fit's result.json (fitted poses and statistics); "
                                    "without it each pose is located by PnP with the model; "
                                    "a rig's: default RIG.result.json beside the rig model, "
                                    "which `phasecal calibrate` writes")
    p.add_argument("--title", default=None, help="page title")
    p.add_argument("--session", default="not given", help="session name for the header")
    p.add_argument("--rig", default="not given", help="rig name for the header")
    p.add_argument("--cameras", default="not given", help="camera(s) for the header")
    p.add_argument("-o", "--output", required=True, help="output folder")


def pose_labels(paths: list[str]) -> list[str]:
    """A name per maps file: its stem, or folder/stem when stems repeat (pose folders each
    holding a maps.npz)."""
    stems = [Path(m).stem for m in paths]
    if len(set(stems)) == len(stems):
        return stems
    return [f"{Path(m).parent.name}/{Path(m).stem}" for m in paths]


def run(args: argparse.Namespace) -> int:
    """Entry point for `phasecal report`: a rig model's report or a single camera's."""
    rig = rig_model(args.model)
    if rig is not None:
        page, summary = draw_rig_report_files(args, rig)
        write_single_file(page)
        print(f"wrote {page} ({summary}) and {page.parent / SINGLE_FILE} (one self-contained "
              "file)")
        return 0
    check_single_camera_inputs(args)
    model_path = Path(args.model)
    model = load_model(model_path)
    out = Path(args.output)
    labels = pose_labels([*args.maps, *args.heldout_maps])
    header = ReportHeader(
        title=args.title or f"Calibration report: {model_path.name} ({model.type_name})",
        session=args.session, rig=args.rig, cameras=args.cameras,
        date="model written " + time.strftime("%Y-%m-%d %H:%M UTC",
                                              time.gmtime(model_path.stat().st_mtime)),
        software=f"phasecal {phasecal_version()}", poses_used=labels[:len(args.maps)],
        heldout=labels[len(args.maps):])
    downloads = write_downloads(model, model_path, out)
    inputs = ReportInputs(model=str(model_path), plan=args.plan, maps=list(args.maps),
                          heldout_maps=list(args.heldout_maps), result=args.result,
                          labels=labels, header=header, downloads=downloads)
    names = draw_report(inputs, str(out))
    write_single_file(out / "report.html")
    files = sum(d.href is not None for d in downloads)
    print(f"wrote {out / 'report.html'} ({len(names) - 1} images, {files} downloads) and "
          f"{out / SINGLE_FILE} (one self-contained file)")
    return 0


def rig_model(path: str) -> RigModel | None:
    """The rig in `path` if it is a rig model (phasecal.rig/1), else None (`load_model`
    reads it, or names what is wrong with it)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return rig_from_dict(data, source=path) if is_rig_document(data) else None


def check_single_camera_inputs(args: argparse.Namespace) -> None:
    """A one-line error for what a single camera's report cannot take: CAMERA/VIEW=
    prefixes, observations, held-out views by name, no maps or no plan."""
    if rig_requested(args):
        raise UserError(f"--maps: {args.model} is a single-camera model; CAMERA/VIEW= prefixes "
                        "are for a rig model (phasecal.rig/1)")
    for flag in ("observations", "heldout_view"):
        if getattr(args, flag):
            raise UserError(f"--{flag.replace('_', '-')}: for a rig model (phasecal.rig/1); "
                            f"{args.model} is a single-camera model")
    if not args.maps:
        raise UserError("--maps: the training poses' maps are needed")
    if not args.plan:
        raise UserError("--plan: needed for a single camera's report (the screen geometry)")


def write_single_file(page: Path) -> None:
    """The self-contained copy of a drawn page beside it (images inlined, links as text)."""
    text = page.read_text(encoding="utf-8")
    (page.parent / SINGLE_FILE).write_text(self_contained(text, page.parent), encoding="utf-8")
