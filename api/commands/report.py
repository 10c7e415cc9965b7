"""`phasecal report`: the calibration report (HTML page + PNGs, the model and its exports
beside it) from a model and its maps."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from api.version import phasecal_version
from calibration import (
    ReportHeader,
    ReportInputs,
    draw_report,
    load_model,
    self_contained,
    write_downloads,
)

SINGLE_FILE = "report-single.html"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True, help="fitted model (phasecal.model/1 JSON)")
    p.add_argument("--plan", required=True, help="pattern plan (for the screen geometry)")
    p.add_argument("--maps", required=True, nargs="+", help="training poses' maps (.npz)")
    p.add_argument("--heldout-maps", nargs="+", default=[], metavar="NPZ",
                   help="held-out poses' maps, validated with the model")
    p.add_argument("--result", help="the fit's result.json (fitted poses and statistics); "
                                    "without it each pose is located by PnP with the model")
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
    page = (out / "report.html").read_text(encoding="utf-8")
    (out / SINGLE_FILE).write_text(self_contained(page, out), encoding="utf-8")
    files = sum(d.href is not None for d in downloads)
    print(f"wrote {out / 'report.html'} ({len(names) - 1} images, {files} downloads) and "
          f"{out / SINGLE_FILE} (one self-contained file)")
    return 0
