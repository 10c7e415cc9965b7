"""The joint refinement: hand-eye X and world-target Y with every robot pose's own error.

A maximum-likelihood fit of Y = C_i X A_i over all views: the unknowns are X, Y and each
view's robot pose error (drawn with the robot's stated 1-sigma repeatability, rotation in
the base frame and position of the flange origin), the data are the camera's target poses
A_i weighted by their joint covariance. The 12x12 covariance of (X, Y) comes from the whitened
Jacobian at the solution, with the robot errors marginalized, and is scaled up by chi2/dof
when the residuals exceed what the stated noise explains.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from calibration.handeye.classical import Mount, chain
from calibration.handeye.rigid import Rigid, batch_matrices, batch_rotvecs
from calibration.handeye.view_poses import ViewPoses


@dataclass(frozen=True)
class JointSolution:
    """X, Y, the covariance of their perturbations (12x12: X's 6 then Y's 6), the fit's
    chi2/dof and the factor the covariance was scaled by (>= 1)."""

    hand_eye: Rigid
    world_target: Rigid
    covariance: np.ndarray
    chi2_per_dof: float
    covariance_scale: float
    robot_errors: np.ndarray  # (N, 6): each view's estimated robot pose error


def robot_sigmas(repeatability_mm: float, repeatability_deg: float) -> np.ndarray:
    """The 1-sigma of a robot pose error's perturbation (rad x3, mm x3)."""
    return np.array([np.radians(repeatability_deg)] * 3 + [repeatability_mm] * 3)


def whitener(covariance: np.ndarray) -> np.ndarray:
    """W with W.T @ W = inverse(covariance): W @ e is e in units of its sigma. Directions
    the covariance leaves (numerically) without variance get a weight of 1e6 times the
    largest sigma's inverse instead of an infinite one."""
    vals, vecs = np.linalg.eigh((covariance + covariance.T) / 2)
    vals = np.maximum(vals, vals.max() * 1e-12)
    return (vecs / np.sqrt(vals)).T


def refine(mount: Mount, flange: list[Rigid], views: ViewPoses, repeatability_mm: float,
           repeatability_deg: float, start: tuple[Rigid, Rigid]) -> JointSolution:
    """Refine (X, Y) from `start`; `flange[i]` and `views.poses[i]` are one view."""
    n = len(views.poses)
    sig = robot_sigmas(repeatability_mm, repeatability_deg)
    weight = whitener(views.covariance)  # all views at once: they share the intrinsics' error
    f_rot = np.stack([f.rotation for f in flange])
    f_t = np.stack([f.translation for f in flange])
    m_rot = np.stack([v.rotation for v in views.poses])
    m_t = np.stack([v.translation for v in views.poses])
    x0, y0 = start

    def residual(p: np.ndarray) -> np.ndarray:
        x, y = x0.perturbed(p[:6]), y0.perturbed(p[6:12])
        deltas = p[12:].reshape(n, 6)
        rot = batch_matrices(deltas[:, :3]) @ f_rot  # the robot's true flange poses
        t = f_t + deltas[:, 3:]
        if mount == "eye-in-hand":  # C^-1 = F^-1
            c_inv_rot, c_inv_t = rot.transpose(0, 2, 1), -np.einsum("nji,nj->ni", rot, t)
        else:  # C^-1 = F
            c_inv_rot, c_inv_t = rot, t
        x_inv = x.inverse()
        # predicted A = X^-1 C^-1 Y
        p_rot = x_inv.rotation @ c_inv_rot @ y.rotation
        p_t = (np.einsum("ij,njk,k->ni", x_inv.rotation, c_inv_rot, y.translation)
               + c_inv_t @ x_inv.rotation.T + x_inv.translation)
        err = np.hstack([batch_rotvecs(p_rot @ m_rot.transpose(0, 2, 1)), p_t - m_t])
        return np.concatenate([weight @ err.ravel(), (deltas / sig).ravel()])

    scale = np.concatenate([[1e-3] * 3 + [1.0] * 3] * (2 + n))
    sol = least_squares(residual, np.zeros(12 + 6 * n), x_scale=scale, method="lm")
    cov = np.linalg.inv(sol.jac.T @ sol.jac)[:12, :12]
    dof = 6 * n - 12
    chi2 = float(sol.fun @ sol.fun / dof) if dof > 0 else float("nan")
    inflate = max(chi2, 1.0) if dof > 0 else 1.0
    return JointSolution(x0.perturbed(sol.x[:6]), y0.perturbed(sol.x[6:12]), cov * inflate,
                         chi2, inflate, sol.x[12:].reshape(n, 6))


def predicted_target(mount: Mount, solution: JointSolution, flange: Rigid) -> Rigid:
    """Where the camera should see the target from this flange pose: X^-1 C^-1 Y."""
    return (solution.hand_eye.inverse() @ chain(mount, flange).inverse()
            @ solution.world_target)
