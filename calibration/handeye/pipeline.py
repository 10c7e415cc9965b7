"""Hand-eye from robot poses (phasecal.robot-poses/1) and one maps or observations file per
view; the camera is fitted first (the model asked for), then each view's target pose is
refitted with the camera fixed and the poses' joint covariance found
(`view_poses.fit_view_poses`), then `solve.estimate_handeye`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from calibration.fit.dispatch import calibrate
from calibration.fit.result import CalibrationResult
from calibration.fit.sparse.calibrate import calibrate_observations
from calibration.handeye.rigid import Rigid
from calibration.handeye.robot_poses import RobotPoses, read_robot_poses
from calibration.handeye.solve import Mount, estimate_handeye, handeye_document
from calibration.handeye.view_poses import (
    ViewData,
    fit_view_poses,
    maps_view,
    observations_view,
)
from calibration.models.base import jsonable
from calibration.shared.maps import DecodedMaps, load_maps
from calibration.shared.observations import TargetObservations, load_observations
from calibration.shared.plan import Plan, read_plan
from calibration.shared.progress import CancelCheck, ProgressFn, check_cancelled


def _camera_stats(result: CalibrationResult, model: str) -> dict[str, Any]:
    st = result.stats
    keep = ("rms_px", "expected_rms_px", "noise_floor_ratio", "model_adequate")
    return jsonable({"model": model, **{k: st[k] for k in keep if k in st}})


def _check_views(names: list[str], robot: RobotPoses) -> None:
    missing = [v for v in names if v not in robot.poses]
    if missing:
        raise ValueError(f"robot poses: no pose for view(s) {', '.join(missing)} (the VIEW "
                         "names of the camera data must match the robot poses' keys)")


def _document(mount: Mount, robot: RobotPoses, result: CalibrationResult, model: str,
              names: list[str], data: list[ViewData], reference_point: np.ndarray,
              progress: ProgressFn | None, cancelled: CancelCheck | None) -> dict[str, Any]:
    """Each view's pose and their covariance with the fitted camera, then the hand-eye."""
    check_cancelled(cancelled, "hand-eye")
    if progress is not None:
        progress(0, 2, "view poses")
    starts = [Rigid(np.asarray(p.rotation), np.asarray(p.translation)) for p in result.poses]
    views = fit_view_poses(result.model, data, starts)
    check_cancelled(cancelled, "hand-eye")
    if progress is not None:
        progress(1, 2, "hand-eye")
    estimate = estimate_handeye(mount, robot.poses, names, views, robot.repeatability_mm,
                                robot.repeatability_deg, reference_point)
    stats = {**_camera_stats(result, model), "view_poses_chi2_per_dof": views.chi2_per_dof,
             "intrinsics_uncertainty_in_view_poses": views.intrinsics_marginalized}
    if progress is not None:
        progress(2, 2, "hand-eye")
    return handeye_document(estimate, result.model.to_dict(), stats,
                            robot.repeatability_mm, robot.repeatability_deg)


def handeye_from_maps(mount: Mount, robot: RobotPoses, plan: Plan, maps: dict[str, DecodedMaps],
                      model: str, *, options: dict[str, Any] | None = None,
                      progress: ProgressFn | None = None,
                      cancelled: CancelCheck | None = None) -> dict[str, Any]:
    """The phasecal.handeye/1 document from decoded maps keyed by view name; the held-out
    error is stated at the screen's center."""
    names = list(maps)
    _check_views(names, robot)
    result = calibrate([maps[v] for v in names], plan.screen, model, options=options,
                       progress=progress, cancelled=cancelled)
    rng = np.random.default_rng(0)
    data = [maps_view(maps[v], plan.screen, rng) for v in names]
    screen = plan.screen
    center = np.array([(screen.width_px - 1) / 2 * screen.pitch_mm[0],
                       (screen.height_px - 1) / 2 * screen.pitch_mm[1], 0.0])
    return _document(mount, robot, result, model, names, data, center, progress, cancelled)


def handeye_from_observations(mount: Mount, robot: RobotPoses,
                              observations: dict[str, TargetObservations], model: str, *,
                              options: dict[str, Any] | None = None,
                              progress: ProgressFn | None = None,
                              cancelled: CancelCheck | None = None) -> dict[str, Any]:
    """The phasecal.handeye/1 document from target observations keyed by view name; the
    held-out error is stated at the centroid of the target points."""
    names = list(observations)
    _check_views(names, robot)
    result = calibrate_observations([observations[v] for v in names], model, options=options,
                                    progress=progress, cancelled=cancelled)
    data = [observations_view(observations[v]) for v in names]
    points = np.vstack([o.target_xyz[o.used()] for o in observations.values()])
    return _document(mount, robot, result, model, names, data, points.mean(axis=0), progress,
                     cancelled)


def handeye_files(mount: Mount, robot_path: str | Path, source: str,
                  paths: dict[str, str], model: str, *, plan_path: str | Path | None = None,
                  options: dict[str, Any] | None = None, progress: ProgressFn | None = None,
                  cancelled: CancelCheck | None = None) -> dict[str, Any]:
    """Hand-eye from files: robot poses JSON and VIEW -> maps.npz (`source` "maps", with the
    plan) or VIEW -> observations.npz (`source` "observations")."""
    robot = read_robot_poses(robot_path)
    if source == "maps":
        if plan_path is None:
            raise ValueError("plan: decoded maps need the pattern plan (--plan)")
        plan = read_plan(plan_path)
        maps = {}
        for view, path in paths.items():
            check_cancelled(cancelled, "hand-eye")
            maps[view] = load_maps(path)
        return handeye_from_maps(mount, robot, plan, maps, model, options=options,
                                 progress=progress, cancelled=cancelled)
    if source == "observations":
        obs = {view: load_observations(path) for view, path in paths.items()}
        return handeye_from_observations(mount, robot, obs, model, options=options,
                                         progress=progress, cancelled=cancelled)
    raise ValueError(f"source: expected maps or observations, got {source!r}")
