"""`phasecal calibrate --observations`: one camera fitted in pixel space to target
observation files (each its own view); `calibrate` hands over here."""

from __future__ import annotations

import argparse

from api.cli import UserError
from api.progress import progress_bar
from calibration import (
    ModelError,
    calibrate_observation_files,
    export_opencv_yaml,
    export_ros_yaml,
    save_model,
)
from calibration.shared.observations import ObservationsError


def run_observations(args: argparse.Namespace, options: dict[str, object]) -> int:
    """Fit, print the statistics (outliers per view, bow, cross-validation), write outputs."""
    for flag in ("heldout", "max_points"):
        if getattr(args, flag, None):
            raise UserError(f"--{flag.replace('_', '-')}: not for --observations (use "
                            "--cross-validate N to check the fit on views it did not see)")
    if args.cross_validate == 1 or args.cross_validate < 0:
        raise UserError(f"--cross-validate: expected >= 2 view sets, got {args.cross_validate}")
    try:
        with progress_bar(f"calibrate {args.model}") as update:
            result = calibrate_observation_files(
                args.observations, args.model, options=options or None,
                cross_validate=args.cross_validate, progress=update)
    except (ObservationsError, ModelError) as exc:
        raise UserError(str(exc)) from None
    save_model(result.model, args.output)
    st = result.stats
    print(f"wrote {args.output}: {args.model}, RMS {st['rms_px']:.4g} px over "
          f"{sum(p['n_points'] for p in st['per_pose'])} points in {len(st['per_pose'])} views, "
          f"sigma {st['sigma_px']:.3g} px{' (estimated)' if st['sigma_estimated'] else ''}, "
          f"{st['outliers']} outliers")
    for pp in st["per_pose"]:
        out = (f", outliers at rows {pp['outliers']}" if pp["outliers"] else "")
        print(f"  view {pp['view']}: RMS {pp['rms_px']:.4g} px, {pp['n_points']} points{out}")
    if "mesh" in st:  # sGCC: hundreds of control values; the mesh and its choice instead
        cu, cv = st["mesh"]["candidates"][-1]["cells"]
        print(f"  mesh {cu}x{cv} cells, "
              f"{st['mesh']['candidates'][-1]['points_per_cell']:.3g} points per cell with "
              f"points; started from {st['start']['model']} (RMS {st['start']['rms_px']:.4g} px)")
    else:
        std = st["param_std"]
        print("  " + ", ".join(f"{k} {v:.6g} +- {std[k]:.2g}" for k, v in zip(
            result.model.param_names(), result.model.get_params(), strict=True) if std[k] > 0))
    tgt = st["target"]
    if tgt["mode"] == "fit":
        print(f"  target bow: x {tgt['bow_x_mm']:.4g} +- {tgt['bow_x_std_mm']:.2g} mm, "
              f"y {tgt['bow_y_mm']:.4g} +- {tgt['bow_y_std_mm']:.2g} mm over "
              f"{tgt['extent_mm'][0]:g} x {tgt['extent_mm'][1]:g} mm")
    sig = st["projection_sigma_px"]
    print(f"  projection 1-sigma: median {sig['median']:.3g} px, max {sig['max']:.3g} px")
    if "cross_validation" in st:
        cv = st["cross_validation"]
        pair = max(cv["pairs"], key=lambda p: p["ratio"])
        print(f"  cross-validation ({len(cv['folds'])} view sets): RMS difference "
              f"{pair['rms_difference_px']:.3g} px, predicted {pair['rms_predicted_px']:.3g} px, "
              f"ratio {cv['ratio']:.3g} -> {cv['verdict'].upper()}")
    if args.report:
        # lazy: matplotlib takes about a second to import, only worth it when a plot is asked
        from calibration import write_residual_report

        write_residual_report(result, args.report)
    if args.uncertainty_png:
        # lazy: matplotlib, as for --report
        from calibration import write_uncertainty_png

        write_uncertainty_png(result, args.uncertainty_png)
    try:
        if args.export_opencv:
            export_opencv_yaml(result.model, args.export_opencv)
        if args.export_ros:
            export_ros_yaml(result.model, args.export_ros)
    except ModelError as exc:  # e.g. an sGCC model has no OpenCV form
        raise UserError(f"{exc} ({args.output} is written)") from None
    return 0
