"""`phasecal calibrate`: fit a camera model to the decoded maps of several poses."""

from __future__ import annotations

import argparse
import json

from api.cli import UserError
from api.commands.calibrate_observations import run_observations
from api.commands.calibrate_rig import add_rig_arguments, rig_requested, run_rig
from api.progress import progress_bar
from calibration import (
    MODEL_NAMES,
    PARAMETRIC,
    DegenerateError,
    calibrate_files,
    export_opencv_yaml,
    export_ros_yaml,
    save_model,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plan", help="pattern plan (phasecal.plan/1 JSON); needed with --maps")
    p.add_argument("--maps", nargs="+", metavar="[CAMERA/VIEW=]PATH",
                   help="decoded maps, one .npz per pose")
    p.add_argument("--observations", nargs="+", metavar="[CAMERA/VIEW=]PATH",
                   help="target observations (phasecal.observations/1, e.g. from `phasecal "
                        "detect`), one .npz per view; parametric models")
    p.add_argument("--uncertainty-png", metavar="PNG",
                   help="observations: draw the projection uncertainty (and the "
                        "cross-validation difference) over the sensor")
    p.add_argument("--cross-validate", type=int, default=0, metavar="N",
                   help="observations: also fit N (>= 2) disjoint sets of the views and compare "
                        "their projections with the difference their uncertainties predict")
    p.add_argument("--model", required=True, action="append",
                   help="model name, e.g. opencv5; a rig (CAMERA/VIEW= inputs): NAME for every "
                        "camera and/or CAMERA=NAME, repeatable")
    p.add_argument("-o", "--output", required=True, help="output model.json")
    p.add_argument("--heldout", type=int, nargs="+", default=[], metavar="POSE",
                   help="pose indices (0-based, --maps order) left out of the fit and validated")
    p.add_argument("--max-points", type=int,
                   help="points per pose given to the solver (parametric models only; the "
                        "generic models use every valid pixel)")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="model option, VALUE as JSON (e.g. cells=[8,8], central=false); "
                        "repeatable; see docs/calibration.md and docs/generic.md")
    p.add_argument("--report", help="write a residual plot PNG here")
    p.add_argument("--export-opencv", metavar="YAML", help="also write OpenCV FileStorage YAML")
    p.add_argument("--export-ros", metavar="YAML", help="also write ROS camera_info YAML")
    add_rig_arguments(p)


def run(args: argparse.Namespace) -> int:
    """Entry point for `phasecal calibrate`: fit, print the statistics, write the outputs."""
    form = input_form(args)
    if form == "rig":
        return run_rig(args, parse_options(args.option))
    if len(args.model) > 1:
        raise UserError("--model: given more than once; several models are for a rig (inputs "
                        "named CAMERA/VIEW=PATH)")
    args.model = args.model[0]
    if form == "observations":
        return run_observations(args, parse_options(args.option))
    if args.model not in MODEL_NAMES:
        raise UserError(f"--model: expected one of {', '.join(MODEL_NAMES)}, got {args.model!r}")
    if (args.export_opencv or args.export_ros) and args.model not in PARAMETRIC:
        flag = "--export-opencv" if args.export_opencv else "--export-ros"
        raise UserError(f"{flag}: a {args.model} model has no OpenCV/ROS form; after fitting, "
                        "use `phasecal export --format opencv-fit|mrcal|remap` instead")
    options = parse_options(args.option)
    if args.max_points is not None:
        if args.model not in PARAMETRIC:
            raise UserError(f"--max-points: applies to the parametric models "
                            f"({', '.join(PARAMETRIC)}); {args.model} uses every valid pixel")
        if args.max_points < 50:
            raise UserError(f"--max-points: expected >= 50, got {args.max_points}")
        options["max_points_per_pose"] = args.max_points
    try:
        with progress_bar(f"calibrate {args.model}") as update:
            result = calibrate_files(args.plan, args.maps, args.model, options=options or None,
                                     heldout=args.heldout, progress=update)
    except DegenerateError as exc:
        raise UserError(f"calibration failed: {exc}") from None
    save_model(result.model, args.output)
    st = result.stats
    print(f"wrote {args.output}: {args.model}, RMS {st['rms_px']:.4g} px "
          f"(noise floor {st['expected_rms_px']:.4g} px, ratio {st['noise_floor_ratio']:.3g}, "
          f"in the screen plane {st.get('noise_floor_ratio_screen', float('nan')):.3g}"
          f"{'' if st['model_adequate'] else ', MODEL INADEQUATE'})")
    for pp in st["per_pose"]:
        print(f"  pose {pp['pose']}: RMS {pp['rms_px']:.4g} px, screen {pp['rms_screen_px']:.4g} "
              f"px, {pp['n_points']} points")
    if "ray_std_rad_median" in st:
        origin = (f", origin median {st['origin_std_mm_median'] * 1e3:.3g} um"
                  if st.get("origin_std_mm_median") else "")
        print(f"  ray 1-sigma: direction median {st['ray_std_rad_median'] * 1e6:.3g} urad "
              f"(max {st['ray_std_rad_max'] * 1e6:.3g}){origin}")
    if st.get("heldout"):
        print(f"  held-out RMS {st['heldout']['rms_px']:.4g} px "
              f"(ratio {st['heldout']['noise_floor_ratio']:.3g})")
    if st.get("mesh_choice"):
        tried = ", ".join(f"{r['cells'][0]}x{r['cells'][1]}: {r['validation_chi2']:.4g}"
                          for r in st["mesh_choice"])
        print(f"  mesh {st['cells'][0]}x{st['cells'][1]} chosen (validation chi2 {tried})")
    scr = st.get("screen") or {}
    if scr.get("mode") == "fit":
        print("  screen: " + ", ".join(
            "glass_mm held (not identifiable)" if k == "glass_mm" and scr.get("glass_held")
            else f"{k} {scr[k]:.4g} +- {scr['std'][k]:.2g}"
            for k in ("bow_x_mm", "bow_y_mm", "twist_mm", "glass_mm")
        ) + f" (glass index {scr['glass_index']:g})")
    for warning in st.get("warnings", []):
        print(f"  warning: {warning}")
    if args.report:
        # lazy: matplotlib takes about a second to import, only worth it when a plot is asked
        from calibration import write_residual_report

        write_residual_report(result, args.report)
    if args.export_opencv:
        export_opencv_yaml(result.model, args.export_opencv)
    if args.export_ros:
        export_ros_yaml(result.model, args.export_ros)
    return 0


def input_form(args: argparse.Namespace) -> str:
    """Which calibration the inputs ask for: "rig" (CAMERA/VIEW= prefixes), "observations"
    or "maps" (one camera, each file its own view); UserError for a combination that is
    neither."""
    if not args.maps and not args.observations:
        raise UserError("inputs: give --maps (with --plan) or --observations")
    if rig_requested(args):
        return "rig"
    if args.maps and args.observations:
        raise UserError("inputs: --maps and --observations together need CAMERA/VIEW= "
                        "prefixes (a rig); one camera takes one kind")
    for flag in ("cross_validate", "uncertainty_png"):
        if getattr(args, flag) and not args.observations:
            raise UserError(f"--{flag.replace('_', '-')}: applies to --observations")
    if args.maps and not args.plan:
        raise UserError("--plan: needed with --maps (the screen the maps are in)")
    return "observations" if args.observations else "maps"


def parse_options(pairs: list[str]) -> dict[str, object]:
    """The `--option KEY=VALUE` model options (of `calibrate` and `demo`) as a dict: VALUE is
    JSON, or a bare string if it is not JSON (`screen=fit` reads as `screen="fit"`)."""
    options: dict[str, object] = {}
    for pair in pairs:
        key, sep, raw = pair.partition("=")
        if not sep or not key:
            raise UserError(f"--option: expected KEY=VALUE, got {pair!r}")
        try:
            options[key] = json.loads(raw)
        except json.JSONDecodeError:
            options[key] = raw
    return options
