"""Ground-truth cameras for the simulated rig: exact rays and projections.

Written independently of `calibration.models` (closed-form formulas, own inverses) so
that a bug in a fitted model cannot hide by appearing on both sides of a test.
Conventions (docs/formats.md): pixel centers at integers, top-left pixel center (0, 0);
camera frame x right, y down, z forward; millimetres.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hw_mocks.camera_base import NEWTON_ITERS, STEP_TOL, TruthCamera, as_points, normalize
from hw_mocks.fisheye_camera import EquidistantFisheye, wide_fisheye

# -- pinhole with OpenCV distortion ---------------------------------------------------


@dataclass
class PinholeCamera(TruthCamera):
    """Pinhole camera with OpenCV distortion (k1, k2, p1, p2, k3[, k4, k5, k6 rational])."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    is_central: bool = field(default=True, init=False)

    def __post_init__(self) -> None:
        """Validate and normalize the fields (errors name the field and what was expected)."""
        d = np.zeros(8)
        coeffs = np.asarray(self.dist, dtype=np.float64).ravel()
        if coeffs.size not in (4, 5, 8):
            raise ValueError(
                f"PinholeCamera.dist: expected 4, 5 or 8 coefficients "
                f"(k1,k2,p1,p2[,k3[,k4,k5,k6]]), got {coeffs.size}"
            )
        d[: coeffs.size] = coeffs
        self._d = d
        self._r2_max = self._monotonic_r2_limit()

    @property
    def camera_matrix(self) -> np.ndarray:
        """The 3x3 intrinsic matrix K."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def _radial(self, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Radial factor and its derivative with respect to r^2."""
        k1, k2, _, _, k3, k4, k5, k6 = self._d
        num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
        if k4 == k5 == k6 == 0:
            return num, dnum
        den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
        return num / den, (dnum * den - num * dden) / (den * den)

    def _monotonic_r2_limit(self) -> float:
        """Largest r^2 of normalized coords up to which radial distortion stays one-to-one."""
        r = np.linspace(0.0, 4.0, 40001)
        rad, _ = self._radial(r**2)
        rd = r * rad
        bad = np.nonzero((np.diff(rd) <= 0) | (rad[1:] <= 0))[0]
        return float(r[bad[0]] ** 2) if bad.size else float(r[-1] ** 2)

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalized undistorted -> distorted coordinates (OpenCV formula)."""
        _, _, p1, p2, *_ = self._d
        r2 = x * x + y * y
        rad, _ = self._radial(r2)
        xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd

    def _distort_with_jacobian(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        """`distort` and its partial derivatives (dxd/dx, dxd/dy = dyd/dx, dyd/dy)."""
        _, _, p1, p2, *_ = self._d
        xx, yy, xy = x * x, y * y, x * y
        r2 = xx + yy
        rad, drad = self._radial(r2)
        xd = x * rad + 2 * p1 * xy + p2 * (r2 + 2 * xx)
        yd = y * rad + p1 * (r2 + 2 * yy) + 2 * p2 * xy
        a = rad + 2 * xx * drad + 2 * p1 * y + 6 * p2 * x
        b = 2 * xy * drad + 2 * p1 * x + 2 * p2 * y
        d = rad + 2 * yy * drad + 6 * p1 * y + 2 * p2 * x
        return xd, yd, a, b, d

    def undistort(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Invert `distort` by vectorized Newton iteration (to ~1e-15 in normalized units)."""
        rad0, _ = self._radial(xd * xd + yd * yd)
        rad0 = np.where(rad0 > 0.2, rad0, 1.0)  # beyond a sane radial factor: start at xd
        x, y = xd / rad0, yd / rad0  # one fixed-point step: saves a Newton iteration
        for _ in range(NEWTON_ITERS):
            fx_, fy_, a, b, d = self._distort_with_jacobian(x, y)
            ex, ey = fx_ - xd, fy_ - yd
            det = a * d - b * b
            dx = (d * ex - b * ey) / det
            dy = (a * ey - b * ex) / det
            x -= dx
            y -= dy
            if np.nanmax(np.abs(dx) + np.abs(dy), initial=0.0) < STEP_TOL:
                break
        fx_, fy_ = self.distort(x, y)
        bad = (x * x + y * y > self._r2_max) | (np.hypot(fx_ - xd, fy_ - yd) > 1e-12)
        return np.where(bad, np.nan, x), np.where(bad, np.nan, y)

    def rays(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coords -> (zero origins, unit directions) through the optical center."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        x, y = self.undistort((u - self.cx) / self.fx, (v - self.cy) / self.fy)
        d = normalize(np.stack([x, y, np.ones_like(x)], axis=-1))
        return np.zeros_like(d), d

    def project(self, points: np.ndarray) -> np.ndarray:
        """Points in front of the camera -> distorted pixel coordinates; NaN if not imaged."""
        p = as_points(points)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = p[:, 0] / z, p[:, 1] / z
        xd, yd = self.distort(x, y)
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)
        ok = (z > 0) & (x * x + y * y <= self._r2_max) & self.in_image(uv)
        uv[~ok] = np.nan
        return uv


def mild_pinhole(width: int = 640, height: int = 480) -> PinholeCamera:
    """A ~60 degree (horizontal) pinhole with mild OpenCV 5-coefficient distortion."""
    f = float((width / 2) / np.tan(np.radians(30.0)))
    return PinholeCamera(
        width,
        height,
        fx=f,
        fy=f * 1.0007,
        cx=(width - 1) / 2 + 0.013 * width,
        cy=(height - 1) / 2 - 0.009 * height,
        dist=(-0.11, 0.045, 4e-4, -3e-4, -0.008),
    )


# -- smooth non-central camera -----------------------------------------------------------


@dataclass
class Bump:
    """A local Gaussian deviation of ray direction: center (u, v) px, width px, amplitude rad."""

    u: float
    v: float
    width_px: float
    amplitude_rad: tuple[float, float]


@dataclass
class NonCentralCamera(TruthCamera):
    """A central base camera plus smooth direction (~1e-3 rad) and origin (~0.3 mm) deviations.

    With `bumps`, local Gaussian direction deviations put the ray field outside every
    parametric family (and outside coarse spline meshes).
    """

    base: PinholeCamera | EquidistantFisheye
    direction_amplitude_rad: float = 1.5e-3
    origin_amplitude_mm: float = 0.3
    bumps: Sequence[Bump] = ()
    is_central: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        """Take the image size from the base camera."""
        self.width = self.base.width
        self.height = self.base.height

    def _st(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sensor coordinates scaled to about [-1, 1]."""
        return (u - (self.width - 1) / 2) / (self.width / 2), (v - (self.height - 1) / 2) / (
            self.height / 2
        )

    def _deviation(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Small tangent-plane angles (a, b) rad added to the base direction at (u, v)."""
        s, t = self._st(u, v)
        amp = self.direction_amplitude_rad
        a = amp * (0.6 * s * t + 0.4 * np.sin(1.7 * s + 0.3) * np.cos(1.1 * t) - 0.25 * t * t)
        b = amp * (0.5 * s * s - 0.3 * np.cos(1.3 * t - 0.2) * s + 0.35 * np.sin(1.2 * t) * t)
        for bump in self.bumps:
            g = np.exp(-((u - bump.u) ** 2 + (v - bump.v) ** 2) / (2 * bump.width_px**2))
            a = a + bump.amplitude_rad[0] * g
            b = b + bump.amplitude_rad[1] * g
        return a, b

    def _origin(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Ray origin (...,3) mm: a smooth surface of about origin_amplitude_mm."""
        s, t = self._st(u, v)
        m = self.origin_amplitude_mm
        ox = m * (0.5 * s + 0.2 * s * t * t)
        oy = m * (0.45 * t + 0.15 * s * s * t)
        oz = m * (0.8 * (s * s + t * t) - 0.3 * s * t)
        return np.stack([ox, oy, oz], axis=-1)

    def rays(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coords -> (origins, unit directions): base ray tilted and displaced smoothly."""
        o, d, imaged = self._rays_unclipped(u, v)
        return np.where(imaged[..., None], o, np.nan), np.where(imaged[..., None], d, np.nan)

    def _rays_unclipped(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, ...]:
        """(origins, directions, imaged): rays also beyond a fisheye base's FOV, and the mask."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        if isinstance(self.base, EquidistantFisheye):
            d0, theta = self.base.directions_unclipped(u, v)
            imaged = theta <= np.radians(self.base.fov_deg) / 2 + 1e-12
        else:
            d0 = self.base.rays(u, v)[1]
            imaged = np.isfinite(d0[..., 0])
        a, b = self._deviation(u, v)
        # Tangent basis of d0: the camera's x and y axes carried along the great circle
        # from the optical axis to d0 (smooth everywhere except straight backwards).
        dx, dy, dz = d0[..., 0], d0[..., 1], d0[..., 2]
        c = 1.0 / (1.0 + dz)
        e1 = np.stack([1 - dx * dx * c, -dx * dy * c, -dx], axis=-1)
        e2 = np.stack([-dx * dy * c, 1 - dy * dy * c, -dy], axis=-1)
        d = normalize(d0 + a[..., None] * e1 + b[..., None] * e2)
        o = np.where(np.isnan(d), np.nan, self._origin(u, v))
        return o, d, imaged & np.isfinite(d[..., 0])

    def _residual(self, uv: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Base-pixel difference between the ray direction at uv and the direction to p."""
        o, d, _ = self._rays_unclipped(uv[:, 0], uv[:, 1])
        base_proj = self._base_unclipped
        return base_proj(d) - base_proj(p - o)

    def _base_unclipped(self, dirs: np.ndarray) -> np.ndarray:
        """Base-camera projection of directions ignoring sensor limits."""
        if isinstance(self.base, EquidistantFisheye):
            return self.base.project_unclipped(dirs)
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = dirs[:, 0] / dirs[:, 2], dirs[:, 1] / dirs[:, 2]
        xd, yd = self.base.distort(x, y)
        return np.stack([self.base.fx * xd + self.base.cx, self.base.fy * yd + self.base.cy], 1)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Points -> pixels by a vectorized chord-Newton on the ray condition; NaN if not imaged.

        The Jacobian (central differences) is taken at the start point only: the map is a
        small smooth perturbation of the identity, so the iteration still contracts fast.
        """
        p = as_points(points)
        uv = self._base_unclipped(p)
        h = 1e-3
        active = np.all(np.isfinite(uv), axis=1)
        q0, p0 = uv[active], p[active]
        hu, hv = np.array([h, 0.0]), np.array([0.0, h])
        ju = (self._residual(q0 + hu, p0) - self._residual(q0 - hu, p0)) / (2 * h)
        jv = (self._residual(q0 + hv, p0) - self._residual(q0 - hv, p0)) / (2 * h)
        jac = np.full((len(p), 2, 2), np.nan)
        jac[active] = np.stack([ju, jv], axis=2)
        for _ in range(40):
            idx = np.nonzero(active)[0]
            if idx.size == 0:
                break
            r = self._residual(uv[idx], p[idx])
            step = np.linalg.solve(jac[idx], r[..., None])[..., 0]
            uv[idx] -= step
            size = np.hypot(step[:, 0], step[:, 1])
            active[idx] = np.isfinite(size) & (size > 1e-11)
        o, d = self.rays(uv[:, 0], uv[:, 1])
        w = p - o
        along = np.sum(w * d, axis=1)
        miss = np.linalg.norm(w - along[:, None] * d, axis=1)
        ok = self.in_image(uv) & (along > 0) & (miss <= 1e-9 * np.maximum(along, 1.0))
        uv[~ok] = np.nan
        return uv


def smooth_noncentral(width: int = 640, height: int = 480, bumps: bool = False) -> NonCentralCamera:
    """A mild pinhole made non-central by smooth ray deviations; `bumps` adds local ones."""
    base = mild_pinhole(width, height)
    extra: tuple[Bump, ...] = ()
    if bumps:
        extra = (
            Bump(0.3 * width, 0.35 * height, 0.04 * width, (1.2e-3, -0.8e-3)),
            Bump(0.7 * width, 0.6 * height, 0.05 * width, (-0.9e-3, 1.1e-3)),
            Bump(0.55 * width, 0.2 * height, 0.03 * width, (0.7e-3, 0.9e-3)),
        )
    return NonCentralCamera(base, bumps=extra)


# -- named cameras (rig configs refer to truth cameras by name) --------------------------

CAMERA_FACTORIES = {
    "mild_pinhole": mild_pinhole,
    "wide_fisheye": wide_fisheye,
    "smooth_noncentral": smooth_noncentral,
}


def make_truth_camera(model: str, width: int, height: int, **params: object) -> TruthCamera:
    """Build a named truth camera (`CAMERA_FACTORIES`), e.g. from a simulated rig's config."""
    if model not in CAMERA_FACTORIES:
        raise ValueError(
            f"camera.model: unknown truth camera {model!r}; "
            f"choose one of {sorted(CAMERA_FACTORIES)}"
        )
    if width <= 0 or height <= 0:
        raise ValueError(f"camera.width/height: expected positive pixels, got {width}x{height}")
    try:
        return CAMERA_FACTORIES[model](width, height, **params)  # type: ignore[operator]
    except TypeError as exc:
        raise ValueError(f"camera: bad parameters for {model!r}: {exc}") from None
