"""The one calibration entry point for the CLI and the REST service: look the model up in the
registry (`calibration.fit.registry`), check its options and pose count, run its fit."""

from __future__ import annotations

from typing import Any

from calibration.fit.registry import model_spec
from calibration.fit.result import CalibrationResult
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import ScreenGeometry
from calibration.shared.progress import CancelCheck, ProgressFn


def calibrate(
    maps: list[DecodedMaps], screen: ScreenGeometry, model: str, *,
    options: dict[str, Any] | None = None, heldout: list[int] | None = None,
    progress: ProgressFn | None = None,
    cancelled: CancelCheck | None = None,
) -> CalibrationResult:
    """Fit `model` to the poses not in `heldout`; report training and held-out statistics."""
    spec = model_spec(model)
    opts = spec.parse_options(options)
    check_pose_count(spec.name, len(maps), len(set(heldout or [])))
    return spec.fit(list(maps), screen, model, options=opts, heldout=heldout, progress=progress,
                    cancelled=cancelled)


def check_pose_count(model: str, given: int, held_out: int) -> None:
    """ValueError unless `given` poses minus `held_out` reach the model's minimum."""
    need, train = model_spec(model).min_poses, given - held_out
    if train < need:
        raise ValueError(f"maps: {model} needs >= {need} poses to fit, got {train} training "
                         f"poses ({given} given, {held_out} held out)")
