"""`phasecal intrinsics`: quick closed-form K from rectangles in images or from decoded poses."""

from __future__ import annotations

import argparse
import json

import cv2
import numpy as np

from api.cli import UserError
from calibration import (
    DegenerateError,
    OpenCV5Model,
    intrinsics_from_images,
    intrinsics_from_maps,
    read_white_flat,
    save_model,
)
from calibration.shared.maps import load_maps
from calibration.shared.plan import read_plan


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--method", required=True, choices=["rectangle", "selfcal", "rotation"],
                   help="rectangle: vanishing points of one rectangle (screen/card) in >= 4 "
                        "varied views (Lu & Whangbo, 'A Practical Camera Calibration System "
                        "on Mobile Phones'); selfcal: vanishing points of two non-parallel "
                        "rectangles, camera moving and turning freely, >= 3 images (Chang, "
                        "Wang & Wang, 'Camera Self-calibration Based on the Vanishing "
                        "Points'); rotation: camera turning in place (pan-tilt), >= 3 images "
                        "(Hartley's rotating-camera self-calibration)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", nargs="+", metavar="IMG",
                     help="grey images (PNG/TIFF, or 2-D .npy) of bright rectangles on dark")
    src.add_argument("--frames", nargs="+", metavar="FRAMES",
                     help="captured poses (FRAMES.npy or frame folders): their white flats")
    src.add_argument("--maps", nargs="+", metavar="MAPS", help="decoded poses (maps.npz)")
    p.add_argument("--plan", help="pattern plan (needed with --frames and --maps)")
    p.add_argument("--square-pixels", action="store_true",
                   help="rectangle: assume fx = fy (needs >= 3 views instead of 4)")
    p.add_argument("--zero-skew", action="store_true",
                   help="selfcal: fix the skew to 0 in the maximum-likelihood refinement")
    p.add_argument("-o", "--output", required=True, help="output intrinsics JSON")
    p.add_argument("--model-out", metavar="MODEL",
                   help="also write a distortion-free opencv5 phasecal.model/1 (for project, "
                        "export, or as a start; the skew is dropped)")


def _read_image(path: str) -> np.ndarray:
    if path.lower().endswith(".npy"):
        img = np.load(path, allow_pickle=False)
    else:
        img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise UserError(f"{path}: not a readable image")
    if img.ndim != 2:
        raise UserError(f"{path}: expected a single-channel (grey) image, got shape {img.shape}")
    return img


def run(args: argparse.Namespace) -> int:
    if (args.frames or args.maps) and not args.plan:
        raise UserError("--plan: required with --frames and --maps")
    try:
        if args.maps:
            plan = read_plan(args.plan)
            est = intrinsics_from_maps([load_maps(m) for m in args.maps], plan.screen,
                                       args.method, square_pixels=args.square_pixels)
        else:
            if args.images:
                images = [_read_image(p) for p in args.images]
            else:
                plan = read_plan(args.plan)
                images = [read_white_flat(f, plan) for f in args.frames]
            est = intrinsics_from_images(images, args.method, square_pixels=args.square_pixels,
                                         zero_skew=args.zero_skew)
    except DegenerateError as exc:
        raise UserError(f"{args.method}: {exc}") from None
    with open(args.output, "w") as fh:
        json.dump(est.to_dict(), fh, indent=1)
    if args.model_out:


        k = est.k.copy()
        k[0, 1] = 0.0
        model = OpenCV5Model(tuple(est.stats["image_size"]), k, np.zeros(5))
        model.stats = {"source": f"phasecal intrinsics --method {args.method}", **est.to_dict()}
        save_model(model, args.model_out)
    d, s = est.to_dict(), est.std
    parts = [f"{p} {d[p]:.2f}" + (f" +- {s[p]:.2f}" if p in s else "")
             for p in ("fx", "fy", "cx", "cy", "skew")]
    print(f"wrote {args.output}: {est.method} from {est.n_views} views: " + ", ".join(parts))
    return 0
