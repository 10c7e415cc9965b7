"""`phasecal calibrate` with `CAMERA/VIEW=PATH` inputs: several cameras fitted jointly into a
rig model (`phasecal.rig/1`). `calibrate` hands over here when its inputs carry prefixes."""

from __future__ import annotations

import argparse
from pathlib import Path

from api.cli import UserError
from api.progress import progress_bar
from calibration import MODEL_NAMES, calibrate_rig_files, save_rig, split_rig_options
from calibration.shared.atomic import write_json_atomic


def add_rig_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments only a rig calibration takes."""
    p.add_argument("--heldout-view", action="append", default=[], metavar="VIEW",
                   help="rig: a view left out of the fit and scored through the extrinsics "
                        "(repeatable)")
    p.add_argument("--reference", metavar="CAMERA",
                   help="rig: the camera whose frame is the rig's (default: the first given)")


def rig_result_path(model: str | Path) -> Path:
    """Where a rig fit's statistics go beside its model (rig.json -> rig.result.json): the
    residuals per camera and view and the held-out scores `phasecal report` draws."""
    p = Path(model)
    return p.with_name(f"{p.stem}.result.json")


def split_prefix(text: str) -> tuple[str, str, str] | None:
    """`CAMERA/VIEW=PATH` -> (camera, view, path); None for a plain path (also one that is an
    existing file whose name happens to contain '/' and '=')."""
    prefix, sep, path = text.partition("=")
    if not sep or Path(text).exists():
        return None
    camera, slash, view = prefix.partition("/")
    if not slash or not camera or not view or "/" in view or not path:
        return None
    return camera, view, path


def rig_requested(args: argparse.Namespace) -> bool:
    """Whether the inputs carry CAMERA/VIEW= prefixes (all or none may: mixing is refused)."""
    paths = [*(args.maps or []), *(getattr(args, "observations", None) or [])]
    tagged = [split_prefix(p) is not None for p in paths]
    if any(tagged) and not all(tagged):
        plain = [p for p, t in zip(paths, tagged, strict=True) if not t]
        raise UserError(f"inputs: either every file has a CAMERA/VIEW= prefix or none; "
                        f"without one: {plain[:3]}")
    return bool(paths) and all(tagged)


def parse_models(values: str | list[str]) -> tuple[str | None, dict[str, str]]:
    """`--model NAME` (every camera) and `--model CAMERA=NAME` (one camera)."""
    default, per_camera = None, {}
    for value in [values] if isinstance(values, str) else values:
        camera, sep, name = value.rpartition("=")
        if name not in MODEL_NAMES:
            raise UserError(f"--model: expected [CAMERA=]NAME with NAME one of "
                            f"{', '.join(MODEL_NAMES)}, got {value!r}")
        if sep and not camera:
            raise UserError(f"--model: expected CAMERA=NAME, got {value!r}")
        if not sep:
            if default is not None:
                raise UserError(f"--model: one model for every camera, got {default!r} and "
                                f"{name!r} (use CAMERA=NAME for one camera)")
            default = name
        else:
            per_camera[camera] = name
    return default, per_camera


def run_rig(args: argparse.Namespace, options: dict[str, object]) -> int:
    """Fit the rig and write its model; `options` are the parsed `--option` pairs (the joint
    fit's own keys go to it, the rest to every camera's model)."""
    export = ("not for a rig; after fitting use `phasecal export --model RIG --camera CAMERA` "
              "(or --cameras A,B --format opencv-stereo)")
    refused = {"export_opencv": export, "export_ros": export,
               "report": "a rig's report is a page: after fitting use `phasecal report "
                         "--model RIG` with the same CAMERA/VIEW= inputs",
               "uncertainty_png": "applies to one camera's observations",
               "cross_validate": "applies to one camera's observations",
               "max_points": "a rig takes --option max_points_per_view=N"}
    for flag, why in refused.items():
        if getattr(args, flag, None):
            raise UserError(f"--{flag.replace('_', '-')}: {why}")
    if getattr(args, "heldout", None):
        raise UserError("--heldout: a rig leaves out views by name: use --heldout-view VIEW")
    entries = []
    for kind, paths in (("maps", args.maps or []),
                        ("observations", getattr(args, "observations", None) or [])):
        for text in paths:
            camera, view, path = split_prefix(text)  # type: ignore[misc]  # rig_requested held
            entries.append((camera, view, kind, path))
    default, per_camera = parse_models(args.model)
    cameras = list(dict.fromkeys(e[0] for e in entries))
    unknown = sorted(set(per_camera) - set(cameras))
    if unknown:
        raise UserError(f"--model: no inputs for camera(s) {unknown}; cameras: {cameras}")
    missing = [c for c in cameras if c not in per_camera and default is None]
    if missing:
        raise UserError(f"--model: no model for camera(s) {missing} (give --model NAME for "
                        "every camera or --model CAMERA=NAME)")
    models = {c: per_camera.get(c, default) for c in cameras}
    rig_opts, model_opts = split_rig_options(options)
    with progress_bar("calibrate rig") as update:
        result = calibrate_rig_files(
            args.plan, entries, models, reference=args.reference, options=rig_opts,
            model_options={c: model_opts for c in cameras},
            heldout_views=args.heldout_view, progress=update)
    save_rig(result.rig, args.output)
    stats_path = rig_result_path(args.output)
    write_json_atomic(stats_path, {"stats": result.json_stats()})
    st = result.stats
    print(f"wrote {args.output}: rig of {len(cameras)} cameras, reference {st['reference']}, "
          f"reduced chi2 {st['reduced_chi2']:.3g}, {st['n_points']} points "
          f"({st['outliers_dropped']} outliers dropped); the fit's statistics in {stats_path}")
    for cam, ex in st["extrinsics"].items():
        if cam == st["reference"]:
            continue
        print(f"  {cam}: baseline {ex['baseline_mm']:.2f} mm, 1-sigma rotation "
              f"{max(ex['rotation_sigma_mrad']):.3g} mrad, translation "
              f"{max(ex['translation_sigma_mm']):.3g} mm")
    if st["intrinsics_fixed"]:
        print(f"  intrinsics held from each camera's own fit: {', '.join(st['intrinsics_fixed'])}")
        carried = st.get("intrinsics_rays_in_covariance") or []
        print(f"  their rays' uncertainty in the extrinsics' sigma: "
              f"{', '.join(carried) if carried else 'none (the sigma is a lower bound)'}")
    for row in st.get("heldout", []):
        scores = ", ".join(f"{c} whitened RMS {s['whitened_rms']:.3g}"
                           for c, s in row["cameras"].items() if s["whitened_rms"] is not None)
        print(f"  held-out view {row['view']} (pose from {row['anchor']}): {scores or 'none'}")
    return 0
