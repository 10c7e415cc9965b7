"""Executor task: the next-pose suggestion of a session (fit, prediction, image), written
by a worker so that the server process that paces captures never runs the fit."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from calibration import DEFAULT_MIN_VISIBLE, guidance_png, plan_next_pose, session_points
from calibration.shared.maps import load_maps
from calibration.shared.plan import read_plan


def guidance_task(plan_path: str, maps_paths: list[str], model: str, out_dir: str,
                  header: dict[str, Any], min_visible: float = DEFAULT_MIN_VISIBLE) -> None:
    """Fit `model` to the poses' maps, plan the next pose and write `next-pose.json`
    (`header` plus the suggestion) and `next-pose.png` into `out_dir`; `min_visible`: the
    least part of the suggested screen inside the image. ValueError when the poses do not
    support a fit."""
    plan = read_plan(plan_path)
    maps = [load_maps(p) for p in maps_paths]
    h, w = maps[0].shape
    sug, _ = plan_next_pose(session_points(maps, plan.screen), (w, h), plan.screen, model,
                            min_visible)
    out = Path(out_dir)
    (out / "next-pose.json").write_text(json.dumps({**header, **sug.to_json()}))
    p = sug.placement
    guidance_png(sug.map_before, sug.map_after, p.border_px, (w, h),
                 f"next pose ({model}): {p.words((w, h))}", out / "next-pose.png")
