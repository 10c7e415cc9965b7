"""The held-out check: leave each view out, fit the rest, predict the target pose the camera
should see from that view's robot pose, and compare with what the camera measured.

The error is stated at the target's reference point (mm) and as the angle between the
orientations (deg), beside what the estimated covariances predict for it (the fit's, the
left-out robot pose's and the camera's), so a hand-eye whose stated sigma is honest shows a
normalized error near 1.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.handeye.classical import Mount
from calibration.handeye.joint import JointSolution, predicted_target, refine, robot_sigmas
from calibration.handeye.rigid import Rigid
from calibration.handeye.view_poses import ViewPoses

_STEP = np.array([1e-7] * 3 + [1e-4] * 3)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _prediction_covariance(mount: Mount, sol: JointSolution, flange: Rigid,
                           robot_sig: np.ndarray) -> np.ndarray:
    """6x6 covariance of the predicted target pose from the fit's covariance and the robot
    pose's error (first order, central differences)."""
    base = predicted_target(mount, sol, flange)
    jac = np.zeros((6, 18))
    for k in range(18):
        step = np.zeros(18)
        step[k] = _STEP[k % 6]
        ends = []
        for sign in (1.0, -1.0):
            p = sign * step
            moved = JointSolution(sol.hand_eye.perturbed(p[:6]), sol.world_target.perturbed(
                p[6:12]), sol.covariance, sol.chi2_per_dof, sol.covariance_scale,
                sol.robot_errors)
            ends.append(predicted_target(mount, moved, flange.perturbed(p[12:])).minus(base))
        jac[:, k] = (ends[0] - ends[1]) / (2 * step[k])
    cov = np.zeros((18, 18))
    cov[:12, :12] = sol.covariance
    cov[12:, 12:] = np.diag(robot_sig**2)
    return jac @ cov @ jac.T


def leave_one_out(mount: Mount, flange: list[Rigid], views: ViewPoses,
                  repeatability_mm: float, repeatability_deg: float, full: JointSolution,
                  reference_point: np.ndarray, names: list[str]) -> dict[str, Any]:
    """Per-view and summary held-out errors (see the module's docstring)."""
    robot_sig = robot_sigmas(repeatability_mm, repeatability_deg)
    rows = []
    for k in range(len(views.poses)):
        keep = [i for i in range(len(views.poses)) if i != k]
        sol = refine(mount, [flange[i] for i in keep], views.subset(keep),
                     repeatability_mm, repeatability_deg, (full.hand_eye, full.world_target))
        pred = predicted_target(mount, sol, flange[k])
        meas = views.poses[k]
        err6 = pred.minus(meas)
        # (the left-out pose's correlation with the others through the intrinsics is left out)
        cov6 = _prediction_covariance(mount, sol, flange[k], robot_sig) + views.block(k)
        point = meas.rotation @ reference_point
        err_point = pred.rotation @ reference_point + pred.translation - point - meas.translation
        to_point = np.hstack([-_skew(point), np.eye(3)])
        cov_point = to_point @ cov6 @ to_point.T
        rows.append({
            "view": names[k],
            "error_mm": float(np.linalg.norm(err_point)),
            "error_deg": float(np.degrees(np.linalg.norm(err6[:3]))),
            "expected_mm": float(np.sqrt(np.trace(cov_point))),
            "expected_deg": float(np.degrees(np.sqrt(np.trace(cov6[:3, :3])))),
            "normalized": float(err6 @ np.linalg.solve(cov6, err6) / 6.0),
        })

    def rms(key: str) -> float:
        return float(np.sqrt(np.mean([r[key] ** 2 for r in rows])))

    return {
        "reference_point_mm": reference_point.tolist(),
        "rms_mm": rms("error_mm"), "rms_deg": rms("error_deg"),
        "max_mm": max(r["error_mm"] for r in rows), "max_deg": max(r["error_deg"] for r in rows),
        "expected_rms_mm": rms("expected_mm"), "expected_rms_deg": rms("expected_deg"),
        "normalized_mean": float(np.mean([r["normalized"] for r in rows])),
        "views": rows,
    }
