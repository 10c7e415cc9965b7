"""The joint least squares of a rig: every camera's free model parameters, each camera's pose
in the reference camera's frame and each view's target pose, over whitened residual blocks.

Parameters: per camera its free intrinsics (a camera held fixed has none; an sGCC spline
fitted here moves in the free directions of its gauge) and, except for the reference
camera, its extrinsics (rotation vector rad, t mm; X_cam = R X_ref + t); per view the
target pose in the reference frame (X_ref = R S + t). A block depends on one camera and one
view only, so the Jacobian is built with columns perturbed together across cameras (and
across views): 2 x (largest camera's parameter count + 6) residual evaluations by central
differences. A spline's coefficients are the exception: their columns are the spline
blocks' exact derivatives, and the spline's prior rows (the single-camera sparse fit's)
follow the data's residuals. The covariance is the inverse of the whitened normal matrix
scaled by the reduced chi-square, as in the single-camera fits; the degrees of freedom
count the parameters the data fix (all of them without a prior).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from calibration.fit.rig.blocks import Block
from calibration.fit.rig.transforms import Transform, compose, from_rvec, to_rvec
from calibration.fit.sgcc.gauge import GaugeBasis
from calibration.fit.sparse.sgcc import spline_gauge, spline_prior
from calibration.models.base import CameraModel
from calibration.models.sgcc import SGCCBase

_RELATIVE_STEP = 1e-6  # central-difference step, relative to |parameter| (floor 0.01)


def _gauge_columns(a: np.ndarray, gauge: GaugeBasis) -> np.ndarray:
    """A @ Z: columns over the full parameter vector turned into the gauge's directions."""
    return np.concatenate([a[..., gauge.keep], a[..., gauge.mixed] @ gauge.basis], axis=-1)


@dataclass
class RigCameraState:
    """A camera of the fit: its model and which model parameters the fit moves."""

    model: CameraModel
    free: np.ndarray  # bool mask over model.get_params(); all False: the model is held
    gauge: GaugeBasis | None = None  # a fitted spline: the directions it moves in
    prior: np.ndarray | None = None  # a fitted spline: whitened prior rows over `gauge`

    @classmethod
    def of(cls, model: CameraModel, free: np.ndarray) -> RigCameraState:
        """An sGCC model with free parameters moves its whole spline in its gauge's free
        directions under the spline's prior (the extrinsics then carry the camera frame);
        any other model moves the parameters `free` selects."""
        if not isinstance(model, SGCCBase) or not free.any():
            return cls(model, free)
        gauge = spline_gauge(model)
        return cls(model, np.ones_like(free), gauge, _gauge_columns(spline_prior(model), gauge))

    @property
    def size(self) -> int:
        """Number of parameters the fit moves."""
        return self.gauge.size if self.gauge is not None else int(np.count_nonzero(self.free))

    def params(self) -> np.ndarray:
        """The moved parameters' current values."""
        p = self.model.get_params()
        return self.gauge.reduce_vector(p) if self.gauge is not None else p[self.free]

    def set_params(self, values: np.ndarray) -> None:
        """Put the moved parameters' values into the model."""
        if self.gauge is not None:
            self.model.set_params(self.gauge.expand(values))
            return
        p = self.model.get_params()
        p[self.free] = values
        self.model.set_params(p)

    def held_spline_covariance(self) -> np.ndarray | None:
        """The covariance over `model.get_params()` of an sGCC spline the fit holds at its own
        dense fit's estimate (that fit's, in the same gauge), else None."""
        if self.gauge is None and not self.free.any() and isinstance(self.model, SGCCBase):
            return self.model.covariance
        return None

    def set_covariance(self, cov: np.ndarray) -> None:
        """A fitted spline's model takes the covariance of its moved directions (`cov`, the
        joint fit's, poses and extrinsics marginalized), so its ray sigma is the rig's."""
        if self.gauge is not None:
            assert isinstance(self.model, SGCCBase)
            self.model.covariance = self.gauge.expand_matrix(cov)


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
            k = cam.size
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
        self.n_data = start
        self.prior_rows: dict[str, np.ndarray] = {}
        for name, cam in cameras.items():
            if cam.prior is not None:
                self.prior_rows[name] = np.arange(start, start + cam.prior.shape[0])
                start += cam.prior.shape[0]
        self.n_residuals = start

    # -- the parameter vector ------------------------------------------------------------
    def pack(self, extrinsics: dict[str, Transform], poses: dict[str, Transform]) -> np.ndarray:
        """The vector of the models' current parameters, these extrinsics and view poses."""
        x = np.zeros(self.size)
        for name, cam in self.cameras.items():
            x[self.intrinsics[name]] = cam.params()
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
            if cam.size:
                cam.set_params(x[self.intrinsics[name]])

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
        """All whitened residuals as one vector (the data's, then the priors'); a point the
        model cannot see counts zero."""
        parts = [r.ravel() for r in self.block_residuals(x)]
        parts += [self.cameras[name].prior @ x[self.intrinsics[name]]
                  for name in self.prior_rows]
        out = np.concatenate(parts) if parts else np.zeros(0)
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
        per_camera = {name: np.concatenate([
            self.intrinsics[name] if cam.gauge is None else np.zeros(0, np.intp),
            self.extrinsics.get(name, np.zeros(0, np.intp))])
            for name, cam in self.cameras.items()}
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
        self._spline_columns(x, jac)
        return jac if free is None else jac[:, free]

    def _spline_columns(self, x: np.ndarray, jac: np.ndarray) -> None:
        """The exact columns of every fitted spline's coefficients: its blocks' derivatives
        and its prior rows."""
        for name, cam in self.cameras.items():
            if cam.gauge is None:
                continue
            assert isinstance(cam.model, SGCCBase) and cam.prior is not None
            cols = self.intrinsics[name]
            ext = self.extrinsic(x, name)
            for b, rows in zip(self.blocks, self.rows, strict=True):
                if b.camera == name:
                    d = b.spline_jacobian(cam.model, compose(ext, self.pose(x, b.view)))
                    d = np.nan_to_num(_gauge_columns(d, cam.gauge), nan=0.0, posinf=0.0,
                                      neginf=0.0)
                    jac[np.ix_(rows, cols)] = d.reshape(rows.size, cols.size)
            jac[np.ix_(self.prior_rows[name], cols)] = cam.prior

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
        """(parameter covariance, reduced chi-square) at x. The chi-square is the data's over
        its degrees of freedom: the data's residuals less the parameters they fix,
        trace(J_d^T J_d (J^T J)^-1), which is every parameter when no prior takes part."""
        res = self.residuals(x)[:self.n_data]
        jac = self.jacobian(x)
        scale = np.linalg.norm(jac, axis=0)
        scale[scale == 0] = 1.0
        jn = jac / scale
        normal = jn.T @ jn
        try:
            inv = np.linalg.inv(normal)
        except np.linalg.LinAlgError:
            dof = max(res.size - self.size, 1)
            return np.full((self.size, self.size), np.inf), float(res @ res) / dof
        jp = jn[self.n_data:]
        fixed = float(np.sum(inv * (normal - jp.T @ jp))) if jp.size else float(self.size)
        chi2 = float(res @ res) / max(res.size - fixed, 1.0)
        cov = (inv * chi2 + self._held_spline_share(x, jn, inv)) / np.outer(scale, scale)
        return 0.5 * (cov + cov.T), chi2

    def _held_spline_share(self, x: np.ndarray, jn: np.ndarray, inv: np.ndarray) -> np.ndarray:
        """The held splines' uncertainty carried into the fitted parameters (the "consider"
        covariance, in the columns of `jn`): G Sigma_s G^T with G = (J^T J)^-1 J^T J_s, J_s
        the whitened derivatives of the camera's spline blocks over its coefficients and
        Sigma_s its own fit's covariance. For a linear model it is the joint fit's marginal
        had the spline been fitted with that uncertainty. J^T J_s is summed block by block
        over the columns a block moves (a block's J_s is points x coefficients)."""
        share = np.zeros_like(inv)
        self.set_models(x)
        for name, cam in self.cameras.items():
            sigma = cam.held_spline_covariance()
            if sigma is None:
                continue
            assert isinstance(cam.model, SGCCBase)
            ext = self.extrinsic(x, name)
            cross = np.zeros((self.size, sigma.shape[0]))
            for b, rows in zip(self.blocks, self.rows, strict=True):
                if b.camera != name or b.kind != "spline":
                    continue
                d = b.spline_jacobian(cam.model, compose(ext, self.pose(x, b.view)))
                d = np.nan_to_num(d.reshape(rows.size, -1), nan=0.0, posinf=0.0, neginf=0.0)
                jb = jn[rows]
                cols = np.flatnonzero(np.any(jb != 0, axis=0))
                cross[cols] += jb[:, cols].T @ d
            g = inv @ cross
            share += g @ sigma @ g.T
        return share
