"""Rays through the cover glass to the shaped panel: the one tracer of every screen fit.

The parametric fits (calibration/metrology/screen.py, `ScreenModel`) and sGCC
(calibration/fit/sgcc/screen_terms.py, on NumPy or CuPy) trace with this code, so both
fits see the same physics to the last bit. Screen frame (mm): x, y along the pixel
rows/columns, z into the screen. The emitting layer lies at z_s = bow_x (xi^2 - 1/3) +
bow_y (eta^2 - 1/3) + twist xi eta (xi, eta in [-1, 1] over the panel) behind a flat cover
glass of index n (known) and thickness h (fitted) whose front surface is z = -h
(docs/physics.md section 8). A ray with origin o and lateral slope q = d_xy / d_z reaches
the panel at the fixed point Q = o_xy - (h + o_z) q + (z_s(Q) + h) m(q), with
m(q) = q / sqrt(n^2 + (n^2 - 1)|q|^2) its slope inside the glass (Snell).

Arrays are feature-major ((k, n): one row per coordinate, contiguous rows for vector
operations and for the GPU); the array module is a parameter (NumPy by default).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Any

from calibration.shared.plan import ScreenGeometry

N_SCREEN = 4  # bow_x, bow_y, twist, glass thickness (mm)
FIXED_POINT_ITERS = 30
FIXED_POINT_TOL_MM = 1e-11


@dataclass(frozen=True)
class ScreenTrace:
    """Panel geometry (centre and half extents, mm) and the glass index; the screen parameters
    [bow_x, bow_y, twist, glass] (mm, host array) are passed per call, as the fits move them."""

    cx: float
    cy: float
    ax: float
    ay: float
    index: float

    @classmethod
    def of(cls, geometry: ScreenGeometry, index: float) -> ScreenTrace:
        """The tracer of a screen: xi, eta run over [-1, 1] across the panel's outer edges."""
        px, py = geometry.pitch_mm
        return cls(0.5 * (geometry.width_px - 1) * px, 0.5 * (geometry.height_px - 1) * py,
                   0.5 * geometry.width_px * px, 0.5 * geometry.height_px * py, float(index))

    def depth(self, params: Any, x: Any, y: Any) -> tuple[Any, Any, Any]:
        """Normalised coordinates xi, eta and the emitting layer's z_s (mm) at panel points
        (x, y) mm, arrays of any module and shape."""
        bx, by, tw = (float(v) for v in params[:3])
        xi, eta = (x - self.cx) / self.ax, (y - self.cy) / self.ay
        return xi, eta, bx * (xi * xi - 1 / 3) + by * (eta * eta - 1 / 3) + tw * xi * eta

    def _solve(self, xp: ModuleType, params: Any, o: Any, q: Any) -> tuple[Any, Any, Any]:
        """Panel points (2,n), the in-glass slopes m (2,n) and w = |q| / |m| (n,)."""
        h, n2 = float(params[3]), self.index**2
        w = xp.sqrt(n2 + (n2 - 1) * (q[0] * q[0] + q[1] * q[1]))
        m = q / w
        base = o[:2] - (h + o[2]) * q
        pts = base + h * m
        # A contraction of factor |grad z_s| |m| (~1e-3 for real panels): a few steps.
        for _ in range(FIXED_POINT_ITERS):
            new = base + (self.depth(params, pts[0], pts[1])[2] + h) * m
            step = float(xp.max(xp.abs(new - pts))) if pts.size else 0.0
            pts = new
            if step < FIXED_POINT_TOL_MM:
                break
        return pts, m, w

    def points(self, xp: ModuleType, params: Any, o: Any, q: Any) -> Any:
        """Panel points Q (2,n) mm of rays with origins o (3,n) and slopes q = d_xy/d_z (2,n)
        in the screen frame (no Jacobians: residual-only passes)."""
        return self._solve(xp, params, o, q)[0]

    def trace(self, xp: ModuleType, params: Any, o: Any, q: Any) -> tuple[Any, Any, Any, Any]:
        """Panel points Q (2,n) mm of rays with origins o (3,n) and slopes q (2,n), and the
        Jacobians dQ/do (2,3,n), dQ/dq (2,2,n), dQ/dparams (2,4,n)."""
        pts, m, w = self._solve(xp, params, o, q)
        h, n2 = float(params[3]), self.index**2
        xi, eta, zs = self.depth(params, pts[0], pts[1])
        bx, by, tw = (float(v) for v in params[:3])
        gx, gy = (2 * bx * xi + tw * eta) / self.ax, (2 * by * eta + tw * xi) / self.ay
        cc = zs + h
        # A = (I - m g^T)^-1 = I + m g^T / (1 - g.m) (Sherman-Morrison): dQ/d(base).
        den = 1.0 / (1.0 - (gx * m[0] + gy * m[1]))
        a = xp.empty((2, 2, w.size))
        a[0, 0], a[0, 1] = 1.0 + m[0] * gx * den, m[0] * gy * den
        a[1, 0], a[1, 1] = m[1] * gx * den, 1.0 + m[1] * gy * den
        aq = a[:, 0] * q[0] + a[:, 1] * q[1]  # (2,n): A q
        jo = xp.empty((2, 3, w.size))
        jo[:, :2] = a
        jo[:, 2] = -aq
        # dm/dq = I / w - (n^2 - 1) q q^T / w^3; dQ/dq = A (-(h + o_z) I + c dm/dq).
        w3 = (n2 - 1) / (w * w * w)
        d = -(h + o[2]) + cc / w
        inner = xp.empty((2, 2, w.size))
        inner[0, 0], inner[1, 1] = d - cc * w3 * q[0] * q[0], d - cc * w3 * q[1] * q[1]
        inner[0, 1] = inner[1, 0] = -cc * w3 * q[0] * q[1]
        jq = (a[:, :, None] * inner[None]).sum(axis=1)
        am = a[:, 0] * m[0] + a[:, 1] * m[1]  # (2,n): dQ/d(z_s) direction
        js = xp.empty((2, N_SCREEN, w.size))
        js[:, 0], js[:, 1] = am * (xi * xi - 1 / 3), am * (eta * eta - 1 / 3)
        js[:, 2] = am * xi * eta
        js[:, 3] = am - aq
        return pts, jo, jq, js

