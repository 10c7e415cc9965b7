"""`phasecal detect`: find a board's corners in images, one `phasecal.observations/1` NPZ per
image that shows it; an image that yields nothing gets one line saying why."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from api.cli import UserError
from calibration import TargetSpec, TargetSpecError, detect_file
from calibration.shared.observations import save_observations


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--target", required=True, metavar="SPEC",
                   help="chessboard:COLSxROWS:SQUARE_MM (inner corners) or "
                        "charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT (squares), e.g. "
                        "chessboard:9x6:25 or charuco:11x8:15:11:DICT_5X5_100")
    p.add_argument("--images", required=True, nargs="+", metavar="IMG",
                   help="image files (PNG, JPEG, TIFF; 8 or 16 bit, colour is made gray)")
    p.add_argument("--camera", default="", help="camera name recorded in each file's meta")
    p.add_argument("-o", "--output", required=True, metavar="DIR",
                   help="folder for the observation files (IMAGE_STEM.npz)")


def run(args: argparse.Namespace) -> int:
    """Detect in every image; exit 1 if none gave a view."""
    try:
        spec = TargetSpec.parse(args.target)
    except TargetSpecError as exc:
        raise UserError(f"--target: {exc}") from None
    stems = [Path(p).stem for p in args.images]
    dupes = sorted({s for s in stems if stems.count(s) > 1})
    if dupes:
        raise UserError(f"--images: several images named {dupes[0]!r} would write the same "
                        f"{dupes[0]}.npz")
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise UserError(f"-o: {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    written = 0
    for path in args.images:
        found = detect_file(path, spec, camera=args.camera)
        if found.observations is None:
            print(f"{path}: nothing detected: {found.reason}", file=sys.stderr)
            continue
        target = out / f"{Path(path).stem}.npz"
        save_observations(found.observations, target)
        written += 1
        print(f"{path}: {found.observations.used_count()} corners -> {target}")
    if not written:
        raise UserError(f"no image showed the target {spec.describe()} "
                        f"({len(args.images)} tried)")
    print(f"wrote {written} of {len(args.images)} views to {out}")
    return 0
