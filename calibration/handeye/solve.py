"""The whole hand-eye estimate from robot poses and the camera's per-view target poses, and
its phasecal.handeye/1 document: the classical methods, the best of them (by the
weighted residual) refined jointly, the held-out check."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.handeye.classical import METHODS, Mount, chain, classical
from calibration.handeye.heldout import leave_one_out
from calibration.handeye.joint import JointSolution, refine, robot_sigmas, whitener
from calibration.handeye.rigid import Rigid
from calibration.handeye.view_poses import ViewPoses

HANDEYE_FORMAT = "phasecal.handeye/1"
MOUNTS = ("eye-in-hand", "eye-to-hand")
MIN_HANDEYE_VIEWS = 4  # three to fit (two independent motions) and one to hold out


@dataclass(frozen=True)
class HandEyeEstimate:
    """The refined solution, every classical method's (X, Y) (or why it failed), the
    held-out check and the views' names in order."""

    mount: Mount
    solution: JointSolution
    classical: dict[str, tuple[Rigid, Rigid] | str]
    start_method: str
    heldout: dict[str, Any]
    views: list[str]


def _cost(mount: Mount, flange: list[Rigid], views: ViewPoses, rep_mm: float,
          rep_deg: float, x: Rigid, y: Rigid) -> float:
    """Sum of squares of the view residuals with the robot's and camera's noise combined
    (a crude stand-in for the joint fit's cost, to pick its start)."""
    robot = np.diag(robot_sigmas(rep_mm, rep_deg) ** 2)
    total = 0.0
    for i, (f, pose) in enumerate(zip(flange, views.poses, strict=True)):
        predicted = x.inverse() @ chain(mount, f).inverse() @ y
        e = whitener(views.block(i) + robot) @ predicted.minus(pose)
        total += float(e @ e)
    return total


def estimate_handeye(mount: Mount, flange: dict[str, Rigid], names: list[str],
                     views: ViewPoses, repeatability_mm: float, repeatability_deg: float,
                     reference_point: np.ndarray) -> HandEyeEstimate:
    """Hand-eye of the views `names` (`views` in that order, each with a robot pose)."""
    if mount not in MOUNTS:
        raise ValueError(f"mount: expected one of {', '.join(MOUNTS)}, got {mount!r}")
    if len(names) < MIN_HANDEYE_VIEWS:
        raise ValueError(f"hand-eye needs >= {MIN_HANDEYE_VIEWS} views with both a robot pose "
                         f"and camera data, got {len(names)}")
    fl = [flange[v] for v in names]
    found: dict[str, tuple[Rigid, Rigid] | str] = {}
    for method in METHODS:
        try:
            found[method] = classical(method, mount, fl, views.poses)
        except (np.linalg.LinAlgError, ValueError) as exc:
            found[method] = f"failed: {str(exc).strip().splitlines()[-1]}"
    costs = {m: _cost(mount, fl, views, repeatability_mm, repeatability_deg, *xy)
             for m, xy in found.items() if not isinstance(xy, str)}
    if not costs:
        raise ValueError("every classical hand-eye method failed: " + "; ".join(
            f"{m}: {e}" for m, e in found.items()))
    best = min(costs, key=lambda m: costs[m])
    start = found[best]
    assert not isinstance(start, str)
    solution = refine(mount, fl, views, repeatability_mm, repeatability_deg, start)
    held = leave_one_out(mount, fl, views, repeatability_mm, repeatability_deg, solution,
                         reference_point, names)
    return HandEyeEstimate(mount, solution, found, best, held, names)


def sigmas(covariance: np.ndarray) -> dict[str, float]:
    """1-sigma of a 6x6 pose covariance: rotation (mrad, the norm's rms) and translation."""
    return {"rotation_mrad": float(np.sqrt(np.trace(covariance[:3, :3])) * 1e3),
            "translation_mm": float(np.sqrt(np.trace(covariance[3:, 3:])))}


def handeye_document(estimate: HandEyeEstimate, camera: dict[str, Any],
                     camera_stats: dict[str, Any], repeatability_mm: float,
                     repeatability_deg: float) -> dict[str, Any]:
    """The phasecal.handeye/1 JSON document."""
    sol = estimate.solution
    cov_x, cov_y = sol.covariance[:6, :6], sol.covariance[6:, 6:]
    methods: dict[str, Any] = {}
    for name, found in estimate.classical.items():
        if isinstance(found, str):
            methods[name] = {"error": found}
            continue
        x, y = found
        methods[name] = {
            "hand_eye": x.to_json(), "world_target": y.to_json(),
            "hand_eye_from_refined": {
                "mm": float(np.linalg.norm(x.translation - sol.hand_eye.translation)),
                "mrad": float(np.linalg.norm(x.minus(sol.hand_eye)[:3]) * 1e3)},
        }
    return {
        "format": HANDEYE_FORMAT,
        "mount": estimate.mount,
        "camera": camera,
        "hand_eye": sol.hand_eye.to_json(cov_x),
        "world_target": sol.world_target.to_json(cov_y),
        "heldout": estimate.heldout,
        "stats": {
            "views": estimate.views,
            "method": f"joint maximum likelihood, started from {estimate.start_method}",
            "hand_eye_sigma": sigmas(cov_x),
            "world_target_sigma": sigmas(cov_y),
            "chi2_per_dof": sol.chi2_per_dof,
            "covariance_scale": sol.covariance_scale,
            "repeatability": {"mm": repeatability_mm, "deg": repeatability_deg},
            "camera_fit": camera_stats,
            "classical_methods": methods,
        },
    }
