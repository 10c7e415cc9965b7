"""One camera's data of one view as whitened residual terms of the joint fit.

Three kinds, all weighted by the data's own uncertainty:

- pixel blocks (a camera whose parameters are fitted): target points projected by the
  model compared with the observed pixels. Decoded maps measure the screen point of a
  pixel, so their screen sigma is carried into the camera image through the local
  Jacobian of the projection (a full 2x2 covariance per point); target observations carry
  `sigma_px / weight`.
- spline blocks: pixel blocks of an sGCC camera, its spline fitted in the joint fit or held
  from its own dense fit. The same pixel residual and weights, but in the closed form of
  the single-camera sparse fit (`sparse/ray_residual.py`: the angle between the point and
  the pixel's ray, turned into pixels by the spline's local Jacobian), which needs no
  iterative projection and gives exact derivatives over the spline's coefficients (a held
  spline's share of the extrinsics' covariance is built from them). Decoded points carry
  their screen sigma through the residual's exact derivative over the point.
- ray blocks (a raygrid camera, whose rays are held from its own fit): each pixel's ray,
  carried into the target's frame, meets the target plane; the miss in mm is divided by
  the decoded sigma in mm. Works for non-central models, and needs no projection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.evaluate import screen_jacobian
from calibration.fit.correspondences import PointSet
from calibration.fit.sparse.ray_residual import (
    PixelRays,
    pixel_rays,
    ray_residual,
    residual_pixels,
)
from calibration.models.base import CameraModel
from calibration.models.sgcc import SGCCBase


@dataclass
class Block:
    """The residual terms of camera `camera` in view `view`."""

    camera: str
    view: str
    kind: str  # "pixel", "spline" or "ray"
    target: np.ndarray  # (N, 3) mm in the target's frame
    pixels: np.ndarray  # (N, 2) camera px
    whiten: np.ndarray  # pixel: (N, 2, 2) inverse Cholesky factor; ray: (N, 2) 1 / sigma mm
    origins: np.ndarray | None = None  # ray: (N, 3) mm, camera frame
    directions: np.ndarray | None = None  # ray: (N, 3) unit, camera frame
    sigma_known: bool = True  # False: observations without sigma_px (scaled from residuals)
    basis: tuple[np.ndarray, ...] | None = None  # spline: the spline basis at the pixels
    rays: PixelRays | None = None  # spline held by the fit: its rays at the pixels

    def __len__(self) -> int:
        """Number of points (each gives two residuals)."""
        return int(self.target.shape[0])

    def subset(self, keep: np.ndarray) -> Block:
        """The points selected by a boolean mask."""
        return Block(self.camera, self.view, self.kind, self.target[keep], self.pixels[keep],
                     self.whiten[keep],
                     None if self.origins is None else self.origins[keep],
                     None if self.directions is None else self.directions[keep],
                     self.sigma_known,
                     None if self.basis is None else tuple(b[keep] for b in self.basis),
                     None if self.rays is None else self.rays.subset(keep))

    def residuals(self, model: CameraModel, to_camera: tuple[np.ndarray, np.ndarray]
                  ) -> np.ndarray:
        """(N, 2) whitened residuals for the target-to-camera transform (R, t); NaN where the
        model does not see a point or a ray misses the plane."""
        rot, t = to_camera
        if self.kind == "pixel":
            uv = model.project(self.target @ rot.T + t)
            return np.einsum("nij,nj->ni", self.whiten, uv - self.pixels)
        if self.kind == "spline":
            points = self.target @ rot.T + t
            if self.rays is not None:
                miss = self.rays.residual_pixels(points)
            else:
                assert isinstance(model, SGCCBase)
                miss = residual_pixels(model, self.pixels, points, self.basis)
            return np.einsum("nij,nj->ni", self.whiten, miss)
        assert self.origins is not None and self.directions is not None
        o = (self.origins - t) @ rot  # R^T (o - t), row-wise
        d = self.directions @ rot
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -o[:, 2] / d[:, 2]
            hit = o[:, :2] + s[:, None] * d[:, :2]
        return (hit - self.target[:, :2]) * self.whiten

    def raw_residuals(self, model: CameraModel, to_camera: tuple[np.ndarray, np.ndarray]
                      ) -> np.ndarray:
        """(N, 2) unwhitened residuals: camera px (pixel blocks) or mm on the target (ray)."""
        w = self.residuals(model, to_camera)
        if self.kind == "ray":
            return w / self.whiten
        return np.linalg.solve(self.whiten, w[:, :, None])[:, :, 0]

    def spline_jacobian(self, model: SGCCBase, to_camera: tuple[np.ndarray, np.ndarray]
                        ) -> np.ndarray:
        """(N, 2, size*C) whitened derivatives of a spline block's residuals over
        `model.get_params()`, exact (the sparse fit's)."""
        assert self.kind == "spline"
        rot, t = to_camera
        rr = ray_residual(model, self.pixels, self.target @ rot.T + t, self.basis)
        return np.einsum("nij,njp->nip", self.whiten, rr.d_coeffs)


def _inverse_cholesky(cov: np.ndarray) -> np.ndarray:
    """(N, 2, 2) L^-1 of each 2x2 covariance C = L L^T (lower triangular L)."""
    a = np.sqrt(cov[:, 0, 0])
    b = cov[:, 1, 0] / a
    c = np.sqrt(np.clip(cov[:, 1, 1] - b * b, 1e-300, None))
    out = np.zeros_like(cov)
    out[:, 0, 0] = 1.0 / a
    out[:, 1, 1] = 1.0 / c
    out[:, 1, 0] = -b / (a * c)
    return out


def _pixel_kind(model: CameraModel, pixels: np.ndarray
                ) -> tuple[str, tuple[np.ndarray, ...] | None]:
    """The kind of pixel terms `model` takes: spline (with the spline basis at the pixels)
    for an sGCC model, else pixel."""
    if isinstance(model, SGCCBase):
        return "spline", model.grid.basis(pixels[:, 0], pixels[:, 1], derivatives=True)
    return "pixel", None


def _residual_screen_jacobian(model: CameraModel, pose: tuple[np.ndarray, np.ndarray],
                              points: PointSet) -> np.ndarray:
    """(N, 2, 2) d(pixel residual)/d(screen px) of decoded points at `pose`: the spline
    residual's exact derivative over the point for an sGCC model, else the projection's by
    central differences."""
    if not isinstance(model, SGCCBase):
        return screen_jacobian(model, pose[0], pose[1], points)
    rot, t = pose
    d_point = ray_residual(model, points.pixels, points.screen_mm @ rot.T + t).d_point
    return d_point @ rot[:, :2] * np.asarray(points.pitch_mm, dtype=np.float64)


def maps_pixel_block(camera: str, view: str, model: CameraModel,
                     pose: tuple[np.ndarray, np.ndarray], points: PointSet,
                     held: bool = False) -> Block:
    """Pixel (or spline) terms of decoded points; the screen sigma is carried into the image
    through the residual's local Jacobian at the start pose (it changes little over the
    fit). A spline the fit `held` keeps its rays at the pixels, computed once."""
    jac = _residual_screen_jacobian(model, pose, points)
    cov = np.einsum("nij,nj,nkj->nik", jac, points.sigma_px**2, jac)
    ok = np.all(np.isfinite(cov.reshape(-1, 4)), axis=1) & (cov[:, 0, 0] > 0)
    ok &= np.linalg.det(np.where(ok[:, None, None], cov, np.eye(2))) > 0
    pts = points.subset(ok)
    kind, basis = _pixel_kind(model, pts.pixels)
    rays = None
    if held and isinstance(model, SGCCBase):
        rays = pixel_rays(model, pts.pixels, basis)
    return Block(camera, view, kind, pts.screen_mm, pts.pixels, _inverse_cholesky(cov[ok]),
                 basis=basis, rays=rays)


def maps_ray_block(camera: str, view: str, model: CameraModel, points: PointSet) -> Block:
    """Ray terms of decoded points through a model whose rays are held fixed."""
    origins, directions = model.unproject(points.pixels)
    ok = np.all(np.isfinite(directions), axis=1) & np.all(np.isfinite(origins), axis=1)
    pitch = np.asarray(points.pitch_mm)
    pts = points.subset(ok)
    return Block(camera, view, "ray", pts.screen_mm, pts.pixels, 1.0 / (pts.sigma_px * pitch),
                 origins[ok], directions[ok])


def observation_block(camera: str, view: str, model: CameraModel, pixels: np.ndarray,
                      target: np.ndarray, weights: np.ndarray, sigma_px: float | None) -> Block:
    """Pixel (or spline) terms of target observations: sigma `sigma_px / weight` (1 / weight
    when the file states no sigma; the fit then scales it from its residuals)."""
    inv = weights / (sigma_px if sigma_px is not None else 1.0)
    whiten = inv[:, None, None] * np.eye(2)[None]
    kind, basis = _pixel_kind(model, pixels)
    return Block(camera, view, kind, target, pixels, whiten, sigma_known=sigma_px is not None,
                 basis=basis)
