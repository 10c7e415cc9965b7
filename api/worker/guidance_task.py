"""Executor tasks of pose guidance, run by a worker so that the server process that paces
captures never runs a fit or reads a pose's whole maps: the next-pose suggestion (fit,
prediction, image) and one pose's outline for the variety check."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from calibration import guidance_png, observe, plan_next_pose, session_points
from calibration.shared.maps import load_maps
from calibration.shared.plan import read_plan


def guidance_task(plan_path: str, maps_paths: list[str], model: str, out_dir: str,
                  header: dict[str, Any]) -> None:
    """Fit `model` to the poses' maps, plan the next pose and write `next-pose.json`
    (`header` plus the suggestion) and `next-pose.png` into `out_dir`; ValueError when the
    poses do not support a fit."""
    plan = read_plan(plan_path)
    maps = [load_maps(p) for p in maps_paths]
    h, w = maps[0].shape
    sug, _ = plan_next_pose(session_points(maps, plan.screen), (w, h), plan.screen, model)
    out = Path(out_dir)
    (out / "next-pose.json").write_text(json.dumps({**header, **sug.to_json()}))
    p = sug.placement
    guidance_png(sug.map_before, sug.map_after, p.border_px, (w, h),
                 f"next pose ({model}): {p.words((w, h))}", out / "next-pose.png")


def observe_task(plan_path: str, maps_path: str, camera_matrix: list[list[float]]
                 ) -> dict[str, Any]:
    """One pose's outline and screen normal (`calibration.observe`) as JSON; ValueError when
    its maps have too few valid points."""
    plan = read_plan(plan_path)
    return observe(load_maps(maps_path), plan.screen, np.asarray(camera_matrix)).to_json()
