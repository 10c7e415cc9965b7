"""Parametric central models: OpenCV pinhole + distortion (5 or rational) and equidistant fisheye.

Projection is closed form; unprojection inverts the distortion by vectorized Newton
iteration (Jacobian by central differences), so `project(unproject(p))` round-trips.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from calibration.models.base import CameraModel, ModelError, register_model

_NEWTON_ITERS = 60
_NEWTON_TOL = 1e-14
_FD_STEP = 1e-7


def _as_points(points: np.ndarray, ncols: int, name: str) -> np.ndarray:
    """Check an (N, ncols) float array and return it as float64."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != ncols:
        raise ValueError(f"{name}: expected shape (N, {ncols}), got {arr.shape}")
    return arr


def _number_list(params: dict[str, Any], key: str, n: int | tuple[int, ...]) -> np.ndarray:
    """Read a list of finite numbers of an allowed length from model params."""
    sizes = (n,) if isinstance(n, int) else n
    raw = params.get(key)
    if not isinstance(raw, list) or len(raw) not in sizes:
        raise ModelError(f"params.{key}: expected a list of {' or '.join(map(str, sizes))} numbers")
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in raw):
        raise ModelError(f"params.{key}: expected numbers, got {raw!r}")
    arr = np.asarray(raw, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ModelError(f"params.{key}: values must be finite")
    return arr


class PinholeFamily(CameraModel):
    """Shared code of the pinhole-style models: K, a distortion vector, Newton inversion."""

    n_dist: ClassVar[int]
    dist_names: ClassVar[tuple[str, ...]]

    def __init__(self, image_size: tuple[int, int], camera_matrix: np.ndarray,
                 dist: np.ndarray | None = None) -> None:
        super().__init__(image_size)
        k = np.asarray(camera_matrix, dtype=np.float64)
        if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ModelError(f"camera_matrix: expected finite 3x3, fx and fy > 0, got {k.tolist()}")
        self.fx, self.fy, self.cx, self.cy = float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(
            k[1, 2]
        )
        d = np.zeros(self.n_dist)
        if dist is not None:
            dd = np.asarray(dist, dtype=np.float64).ravel()
            if dd.size > self.n_dist:
                raise ModelError(f"distortion: at most {self.n_dist} coefficients, got {dd.size}")
            d[: dd.size] = dd
        self.dist = d

    @property
    def camera_matrix(self) -> np.ndarray:
        """The 3x3 intrinsic matrix K (zero skew)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def param_names(self) -> list[str]:
        """Names of the entries of `get_params()`, for per-parameter statistics."""
        return ["fx", "fy", "cx", "cy", *self.dist_names]

    def get_params(self) -> np.ndarray:
        """[fx, fy, cx, cy, distortion...]."""
        return np.concatenate([[self.fx, self.fy, self.cx, self.cy], self.dist])

    def set_params(self, vector: np.ndarray) -> None:
        """Set from the `get_params()` layout."""
        v = np.asarray(vector, dtype=np.float64).ravel()
        if v.size != 4 + self.n_dist:
            raise ModelError(f"{self.type_name}: expected {4 + self.n_dist} params, got {v.size}")
        self.fx, self.fy, self.cx, self.cy = (float(x) for x in v[:4])
        self.dist = v[4:].copy()

    def params_to_json(self) -> dict[str, Any]:
        """K as a nested list plus the named distortion coefficients."""
        return {"camera_matrix": self.camera_matrix.tolist(), "distortion": self.dist.tolist(),
                "distortion_names": list(self.dist_names)}

    @classmethod
    def from_params_json(cls, image_size: tuple[int, int], params: dict[str, Any]) -> CameraModel:
        """Rebuild from `params_to_json()` output."""
        km = params.get("camera_matrix")
        if not (isinstance(km, list) and len(km) == 3 and all(isinstance(r, list) for r in km)):
            raise ModelError("params.camera_matrix: expected a 3x3 nested list")
        rows = [_number_list({"row": r}, "row", 3) for r in km]
        dist = _number_list(params, "distortion", cls.n_dist)
        return cls(image_size, np.stack(rows), dist)

    # -- distortion on normalized coordinates (subclasses) -------------------------------
    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalized ideal (x, y) -> normalized distorted coordinates."""
        raise NotImplementedError

    def _undistort(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Invert `distort` by Newton iteration with a central-difference Jacobian."""
        x, y = xd.copy(), yd.copy()
        h = _FD_STEP
        for _ in range(_NEWTON_ITERS):
            fx_, fy_ = self.distort(x, y)
            ax, ay = self.distort(x + h, y)
            bx, by = self.distort(x - h, y)
            cx_, cy_ = self.distort(x, y + h)
            dx_, dy_ = self.distort(x, y - h)
            a, c = (ax - bx) / (2 * h), (ay - by) / (2 * h)
            b, d = (cx_ - dx_) / (2 * h), (cy_ - dy_) / (2 * h)
            ex, ey = fx_ - xd, fy_ - yd
            det = a * d - b * c
            with np.errstate(divide="ignore", invalid="ignore"):
                sx = (d * ex - b * ey) / det
                sy = (a * ey - c * ex) / det
            x, y = x - sx, y - sy
            if np.nanmax(np.abs(sx) + np.abs(sy), initial=0.0) < _NEWTON_TOL:
                break
        fx_, fy_ = self.distort(x, y)
        bad = ~(np.hypot(fx_ - xd, fy_ - yd) < 1e-10)
        return np.where(bad, np.nan, x), np.where(bad, np.nan, y)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) -> pixels (N, 2); NaN behind the camera."""
        p = _as_points(points, 3, "points")
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = p[:, 0] / z, p[:, 1] / z
        xd, yd = self.distort(x, y)
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)
        uv[~(z > 0)] = np.nan
        return uv

    def unproject(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) -> (zero origins, unit directions); NaN where inversion fails."""
        uv = _as_points(pixels, 2, "pixels")
        x, y = self._undistort((uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy)
        d = np.stack([x, y, np.ones_like(x)], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.zeros_like(d), d


@register_model
class OpenCV5Model(PinholeFamily):
    """OpenCV pinhole with k1, k2, p1, p2, k3 (OpenCV's coefficient order)."""

    type_name = "opencv5"
    n_dist = 5
    dist_names = ("k1", "k2", "p1", "p2", "k3")

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """OpenCV's radial-tangential formula."""
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        return (x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


@register_model
class OpenCVRationalModel(PinholeFamily):
    """OpenCV rational model k1..k6, p1, p2 and thin prism s1..s4 (zero if not fitted)."""

    type_name = "opencv-rational"
    n_dist = 12
    dist_names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """OpenCV's rational radial, tangential and thin-prism formula."""
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = self.dist
        r2 = x * x + y * y
        num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        rad = num / den
        return (x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r2 * r2,
                y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r2 * r2)


@register_model
class FisheyeModel(PinholeFamily):
    """OpenCV fisheye: equidistant r = theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8).

    Sees rays up to 180 degrees off axis: projection uses the angle theta, not x/z.
    """

    type_name = "fisheye"
    n_dist = 4
    dist_names = ("k1", "k2", "k3", "k4")

    def _theta_d(self, t: np.ndarray) -> np.ndarray:
        """Distorted angle as a function of the incidence angle."""
        k1, k2, k3, k4 = self.dist
        t2 = t * t
        return t * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def project(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points -> pixels; NaN at the origin or where theta_d stops increasing."""
        p = _as_points(points, 3, "points")
        rxy = np.hypot(p[:, 0], p[:, 1])
        theta = np.arctan2(rxy, p[:, 2])
        td = self._theta_d(theta)
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(rxy > 0, td / rxy, 0.0)
        uv = np.stack([self.fx * s * p[:, 0] + self.cx, self.fy * s * p[:, 1] + self.cy], axis=1)
        uv[~(np.linalg.norm(p, axis=1) > 0) | (theta > self._theta_limit())] = np.nan
        return uv

    def _theta_limit(self) -> float:
        """Largest angle (<= pi) up to which theta_d is strictly increasing (one-to-one)."""
        t = np.linspace(0.0, np.pi, 4097)
        bad = np.nonzero(np.diff(self._theta_d(t)) <= 0)[0]
        return float(t[bad[0]]) if bad.size else float(np.pi)

    def unproject(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels -> unit directions by Newton on theta_d(theta) = r; NaN beyond the limit."""
        uv = _as_points(pixels, 2, "pixels")
        a = (uv[:, 0] - self.cx) / self.fx
        b = (uv[:, 1] - self.cy) / self.fy
        td = np.hypot(a, b)
        theta = td.copy()
        h = _FD_STEP
        for _ in range(_NEWTON_ITERS):
            der = (self._theta_d(theta + h) - self._theta_d(theta - h)) / (2 * h)
            step = (self._theta_d(theta) - td) / der
            theta = theta - step
            if np.nanmax(np.abs(step), initial=0.0) < _NEWTON_TOL:
                break
        bad = ~(np.abs(self._theta_d(theta) - td) < 1e-10) | (theta > self._theta_limit()) | (
            theta < 0
        )
        with np.errstate(invalid="ignore", divide="ignore"):
            ca = np.where(td > 0, a / td, 1.0)
            sa = np.where(td > 0, b / td, 0.0)
        st = np.sin(theta)
        d = np.stack([st * ca, st * sa, np.cos(theta)], axis=1)
        d[bad] = np.nan
        return np.zeros_like(d), d


PARAMETRIC_MODELS: dict[str, type[PinholeFamily]] = {
    m.type_name: m for m in (OpenCV5Model, OpenCVRationalModel, FisheyeModel)
}
