"""`phasecal decode`: decode one pose's captured frames into `phasecal.maps/1` maps (NPZ)."""

from __future__ import annotations

import argparse

HELP = "decode captured frames (FRAMES.npy or a folder of frame_NNNN.png/.tif) into maps.npz"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plan", required=True, help="pattern plan (phasecal.plan/1 JSON)")
    p.add_argument(
        "--frames", required=True, help="(F, H, W) .npy stack, or a folder of frame_NNNN images"
    )
    p.add_argument(
        "--noise-dn", type=float, metavar="SIGMA",
        help="per-frame camera noise sigma in DN (default: estimated from the fit residuals)",
    )
    p.add_argument(
        "--saturation-dn", type=float,
        help="clipping level in DN (default: the maximum of the frame dtype)",
    )
    p.add_argument(
        "--max-sigma-px", type=float, help="largest accepted 1-sigma in screen px (default 1)"
    )
    p.add_argument("-o", "--output", required=True, help="output maps.npz")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    import numpy as np

    from api.cli import UserError
    from api.progress import progress_bar
    from calibration.decode import DecodeOptions, StreamingDecoder, read_frames
    from calibration.maps import save_maps
    from calibration.plan import read_plan

    plan = read_plan(args.plan)
    source = read_frames(args.frames)
    if source.count != len(plan.frames):
        raise UserError(
            f"{args.frames}: {source.count} frames, but plan {args.plan} has "
            f"{len(plan.frames)} (frame i must show plan frame i)"
        )
    if args.noise_dn is not None and not args.noise_dn > 0:
        raise UserError(f"--noise-dn: must be > 0 DN, got {args.noise_dn}")
    options = DecodeOptions()
    if args.max_sigma_px is not None:
        options = replace(options, max_sigma_px=args.max_sigma_px)
    decoder = StreamingDecoder(
        plan, source.shape, noise=args.noise_dn, saturation_dn=args.saturation_dn, options=options
    )
    with progress_bar("decode") as update:
        for i, frame in enumerate(source):
            decoder.add(i, frame)
            update(i + 1, source.count, "frames")
    maps = decoder.finish({"frames": str(args.frames)})
    save_maps(maps, args.output)
    h, w = maps.shape
    valid = maps.valid_count()
    med = float(np.median(maps.sigma_x[maps.mask])) if valid else float("nan")
    print(
        f"wrote {args.output}: {valid} of {h * w} pixels valid "
        f"({100.0 * valid / (h * w):.1f} %), median sigma_x {med:.3g} px"
    )
    return 0
