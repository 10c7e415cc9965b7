"""A rig calibration from files: decoded maps and target observations named by camera and
view, the plan for the maps' screen, each file read and checked before any fitting."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from calibration.fit.rig.calibrate import calibrate_rig
from calibration.fit.rig.inputs import RigInput
from calibration.fit.rig.options import RigOptions
from calibration.fit.rig.result import RigResult
from calibration.shared.maps import load_maps
from calibration.shared.observations import load_observations
from calibration.shared.plan import read_plan
from calibration.shared.progress import CancelCheck, ProgressFn, check_cancelled


def read_rig_inputs(entries: list[tuple[str, str, str, str | Path]],
                    cancelled: CancelCheck | None = None) -> list[RigInput]:
    """(camera, view, kind "maps" | "observations", path) -> RigInputs."""
    out = []
    for camera, view, kind, path in entries:
        check_cancelled(cancelled, "rig calibration")
        if kind == "maps":
            out.append(RigInput(camera, view, maps=load_maps(path)))
        elif kind == "observations":
            out.append(RigInput(camera, view, observations=load_observations(path)))
        else:
            raise ValueError(f"{path}: kind: expected 'maps' or 'observations', got {kind!r}")
    return out


def calibrate_rig_files(
    plan_path: str | Path | None, entries: list[tuple[str, str, str, str | Path]],
    models: str | Mapping[str, str], *, reference: str | None = None,
    options: RigOptions | dict[str, Any] | None = None,
    model_options: Mapping[str, dict[str, Any]] | None = None,
    heldout_views: list[str] | None = None, progress: ProgressFn | None = None,
    cancelled: CancelCheck | None = None,
) -> RigResult:
    """Read the files and fit the rig (`calibrate_rig`); the plan is needed for maps only."""
    inputs = read_rig_inputs(entries, cancelled)
    screen = None
    if any(i.maps is not None for i in inputs):
        if plan_path is None:
            raise ValueError("--plan: decoded maps need the pattern plan (its screen geometry)")
        screen = read_plan(plan_path).screen
    return calibrate_rig(inputs, models, screen, reference=reference, options=options,
                         model_options=model_options, heldout_views=heldout_views,
                         progress=progress, cancelled=cancelled)
