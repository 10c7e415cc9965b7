"""Executor task: quick closed-form intrinsics of a session's poses (white flats or maps)."""

from __future__ import annotations

from typing import Any

from calibration import (
    intrinsics_from_images,
    intrinsics_from_maps,
    read_white_flat,
)
from calibration.shared.atomic import write_json_atomic
from calibration.shared.maps import load_maps
from calibration.shared.plan import read_plan
from calibration.shared.progress import TaskContext


def intrinsics_task(
    ctx: TaskContext, plan_path: str, paths: list[str], source: str, method: str,
    out_path: str, *, square_pixels: bool = False, zero_skew: bool = False,
) -> dict[str, Any]:
    """Read each pose's white flat frame (`source="flats"`, paths: frame stacks/folders) or
    decoded maps (`source="maps"`), estimate K by `method`, write JSON to `out_path`."""
    plan = read_plan(plan_path)
    total = len(paths) + 1
    inputs = []
    for i, p in enumerate(paths):
        ctx.check_cancelled()
        ctx.progress(i, total, "reading white flats" if source == "flats" else "reading maps")
        inputs.append(read_white_flat(p, plan) if source == "flats" else load_maps(p))
    ctx.progress(len(paths), total, f"estimating ({method})")
    if source == "flats":
        est = intrinsics_from_images(inputs, method, square_pixels=square_pixels,
                                     zero_skew=zero_skew)
    else:
        est = intrinsics_from_maps(inputs, plan.screen, method, square_pixels=square_pixels)
    result = est.to_dict()
    write_json_atomic(out_path, result)
    ctx.progress(total, total, "done")
    return result
