"""The joint least squares of a rig: every camera's free model parameters, each camera's pose
in the reference camera's frame and each view's target pose, over whitened residual blocks.

Parameters: per camera its free intrinsics (a camera held fixed has none) and, except for
the reference camera, its extrinsics (rotation vector rad, t mm; X_cam = R X_ref + t); per
view the target pose in the reference frame (X_ref = R S + t). A block depends on one
camera and one view only, so the Jacobian is built with columns perturbed together across
cameras (and across views): 2 x (largest camera's parameter count + 6) residual
evaluations by central differences. The covariance is the inverse of the whitened normal
matrix scaled by the reduced chi-square, as in the single-camera fits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from calibration.fit.rig.blocks import Block
from calibration.fit.rig.transforms import Transform, compose, from_rvec, to_rvec
from calibration.models.base import CameraModel

_RELATIVE_STEP = 1e-6  # central-difference step, relative to |parameter| (floor 0.01)


@dataclass
class RigCameraState:
    """A camera of the fit: its model and which model parameters the fit moves."""

    model: CameraModel
    free: np.ndarray  # bool mask over model.get_params(); all False: the model is held


class RigProblem:
    """Parameter layout, residuals, Jacobian and covariance of one joint fit."""

    def __init__(self, cameras: dict[str, RigCameraState], reference: str, views: list[str],
                 blocks: list[Block]) -> None:
        self.cameras, self.reference, self.views, self.blocks = cameras, reference, views, blocks
        self.intrinsics: dict[str, np.ndarray] = {}
        self.extrinsics: dict[str, np.ndarray] = {}
        self.poses: dict[str, np.ndarray] = {}
        n = 0
        for name, cam in cameras.items():
            k = int(np.count_nonzero(cam.free))
            self.intrinsics[name] = np.arange(n, n + k)
            n += k
            if name != reference:
                self.extrinsics[name] = np.arange(n, n + 6)
                n += 6
        for view in views:
            self.poses[view] = np.arange(n, n + 6)
            n += 6
        self.size = n
        rows, start = [], 0
        for b in blocks:
            rows.append(np.arange(start, start + 2 * len(b)))
            start += 2 * len(b)
        self.rows = rows
        self.n_residuals = start

    # -- the parameter vector ------------------------------------------------------------
    def pack(self, extrinsics: dict[str, Transform], poses: dict[str, Transform]) -> np.ndarray:
        """The vector of the models' current parameters, these extrinsics and view poses."""
        x = np.zeros(self.size)
        for name, cam in self.cameras.items():
            x[self.intrinsics[name]] = cam.model.get_params()[cam.free]
            if name in self.extrinsics:
                r, t = extrinsics[name]
                x[self.extrinsics[name]] = np.concatenate([to_rvec(r), t])
        for view in self.views:
            r, t = poses[view]
            x[self.poses[view]] = np.concatenate([to_rvec(r), t])
        return x

    def set_models(self, x: np.ndarray) -> None:
        """Put the vector's intrinsics into the models."""
        for name, cam in self.cameras.items():
            if cam.free.any():
                p = cam.model.get_params()
                p[cam.free] = x[self.intrinsics[name]]
                cam.model.set_params(p)

    def extrinsic(self, x: np.ndarray, name: str) -> Transform:
        """Camera `name`'s reference-to-camera transform."""
        if name not in self.extrinsics:
            return np.eye(3), np.zeros(3)
        v = x[self.extrinsics[name]]
        return from_rvec(v[:3]), v[3:].copy()

    def pose(self, x: np.ndarray, view: str) -> Transform:
        """View `view`'s target-to-reference transform."""
        v = x[self.poses[view]]
        return from_rvec(v[:3]), v[3:].copy()

    # -- residuals and Jacobian ----------------------------------------------------------
    def block_residuals(self, x: np.ndarray) -> list[np.ndarray]:
        """(N, 2) whitened residuals of each block (NaN where a point is not seen)."""
        self.set_models(x)
        ext = {name: self.extrinsic(x, name) for name in self.cameras}
        pose = {view: self.pose(x, view) for view in self.views}
        return [b.residuals(self.cameras[b.camera].model, compose(ext[b.camera], pose[b.view]))
                for b in self.blocks]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """All whitened residuals as one vector; a point the model cannot see counts zero."""
        out = np.concatenate([r.ravel() for r in self.block_residuals(x)]) if self.blocks \
            else np.zeros(0)
        return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)

    def _column_groups(self) -> list[list[tuple[int, np.ndarray]]]:
        """Columns perturbed together, each with the residual rows it moves: the k-th
        parameter of every camera, then the k-th parameter of every view."""
        cam_rows = {name: [] for name in self.cameras}
        view_rows = {view: [] for view in self.views}
        for b, rows in zip(self.blocks, self.rows, strict=True):
            cam_rows[b.camera].append(rows)
            view_rows[b.view].append(rows)
        cat = {k: (np.concatenate(v) if v else np.zeros(0, dtype=np.intp))
               for k, v in {**cam_rows, **view_rows}.items()}
        per_camera = {name: np.concatenate([self.intrinsics[name],
                                            self.extrinsics.get(name, np.zeros(0, np.intp))])
                      for name in self.cameras}
        groups = []
        for k in range(max((c.size for c in per_camera.values()), default=0)):
            groups.append([(int(cols[k]), cat[name]) for name, cols in per_camera.items()
                           if k < cols.size])
        for k in range(6):
            groups.append([(int(self.poses[view][k]), cat[view]) for view in self.views])
        return groups

    def jacobian(self, x: np.ndarray, free: np.ndarray | None = None) -> np.ndarray:
        """(residuals, parameters) Jacobian by grouped central differences; only the `free`
        columns (default all)."""
        jac = np.zeros((self.n_residuals, self.size))
        for group in self._column_groups():
            cols = [(c, rows) for c, rows in group if free is None or free[c]]
            if not cols:
                continue
            idx = np.array([c for c, _ in cols])
            h = _RELATIVE_STEP * np.maximum(np.abs(x[idx]), 0.01)
            xp, xm = x.copy(), x.copy()
            xp[idx] += h
            xm[idx] -= h
            diff = self.residuals(xp) - self.residuals(xm)
            for (c, rows), hc in zip(cols, h, strict=True):
                jac[rows, c] = diff[rows] / (2 * hc)
        self.set_models(x)
        return jac if free is None else jac[:, free]

    # -- solve and covariance ------------------------------------------------------------
    def solve(self, x0: np.ndarray, free: np.ndarray | None = None,
              max_iterations: int = 100) -> tuple[np.ndarray, dict[str, object]]:
        """Trust-region least-squares fit of the `free` parameters (default all) from x0;
        returns (x, {iterations (Jacobians built), converged, cost})."""
        mask = np.ones(self.size, dtype=bool) if free is None else free

        def full(y: np.ndarray) -> np.ndarray:
            x = x0.copy()
            x[mask] = y
            return x

        sol = least_squares(lambda y: self.residuals(full(y)), x0[mask],
                            jac=lambda y: self.jacobian(full(y), mask), method="trf",
                            x_scale="jac", max_nfev=max_iterations, xtol=1e-12, ftol=1e-12,
                            gtol=1e-10)
        x = full(sol.x)
        self.set_models(x)
        return x, {"iterations": int(sol.njev), "converged": bool(sol.status > 0),
                   "cost": float(2 * sol.cost)}

    def covariance(self, x: np.ndarray) -> tuple[np.ndarray, float]:
        """(parameter covariance, reduced chi-square) at x."""
        res = self.residuals(x)
        jac = self.jacobian(x)
        dof = max(res.size - self.size, 1)
        chi2 = float(res @ res) / dof
        scale = np.linalg.norm(jac, axis=0)
        scale[scale == 0] = 1.0
        jn = jac / scale
        try:
            cov = np.linalg.inv(jn.T @ jn) / np.outer(scale, scale) * chi2
            cov = 0.5 * (cov + cov.T)
        except np.linalg.LinAlgError:
            cov = np.full((self.size, self.size), np.inf)
        return cov, chi2
