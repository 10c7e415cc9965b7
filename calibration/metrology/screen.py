"""The screen model of the fits: flat and bare, or a shaped panel behind cover glass.

Screen frame (mm): x, y along the pixel rows/columns, z into the screen. With
`screen: "fit"` the emitting layer lies at z_s = bow_x (xi^2 - 1/3) + bow_y (eta^2 - 1/3) +
twist xi eta (xi, eta in [-1, 1] over the panel), behind a flat cover glass of index n
(known) and thickness h (estimated) whose front surface is z = -h; the medium in
between has index n (docs/physics.md section 8). Gauge: the shape terms have zero mean and
zero tilt over the panel, so no plane of it trades with the pose; the pose places the
emitting layer's mean plane. A camera ray with origin o and lateral slope q = d_xy / d_z
reaches the panel at the fixed point Q = o_xy - (h + o_z) q + (z_s(Q) + h) m(q), with
m(q) = q / sqrt(n^2 + (n^2 - 1)|q|^2) the slope inside the glass (Snell).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.plan import ScreenGeometry

SCREEN_MODES = ("flat", "fit")
PARAM_NAMES = ("bow_x_mm", "bow_y_mm", "twist_mm", "glass_mm")
_FIXED_POINT_ITERS = 30
_FIXED_POINT_TOL_MM = 1e-11


@dataclass
class ScreenModel:
    """Screen shape parameters [bow_x, bow_y, twist, glass thickness] (mm), index given."""

    geometry: ScreenGeometry
    mode: str = "flat"
    glass_index: float = 1.52
    params: np.ndarray = field(default_factory=lambda: np.zeros(4))

    def __post_init__(self) -> None:
        """Validate the mode and the index (errors name the option)."""
        if self.mode not in SCREEN_MODES:
            raise ValueError(f"options.screen: expected one of {list(SCREEN_MODES)}, "
                             f"got {self.mode!r}")
        n = self.glass_index
        if isinstance(n, bool) or not isinstance(n, int | float) or not 1.0 <= n <= 3.0:
            raise ValueError(f"options.glass_index: expected a number in [1, 3], got {n!r}")
        self.params = np.asarray(self.params, dtype=np.float64).reshape(4)

    @property
    def n_free(self) -> int:
        """Number of fitted screen parameters (0 for a flat screen)."""
        return 4 if self.mode == "fit" else 0

    def _basis(self, x_mm: np.ndarray, y_mm: np.ndarray) -> tuple[np.ndarray, ...]:
        """Shape basis values (3, N) and their x/y derivatives (3, N) each, per mm."""
        g = self.geometry
        ax, ay = 0.5 * g.width_px * g.pitch_mm[0], 0.5 * g.height_px * g.pitch_mm[1]
        xi = (x_mm - 0.5 * (g.width_px - 1) * g.pitch_mm[0]) / ax
        eta = (y_mm - 0.5 * (g.height_px - 1) * g.pitch_mm[1]) / ay
        zero = np.zeros_like(xi)
        basis = np.stack([xi * xi - 1 / 3, eta * eta - 1 / 3, xi * eta])
        dx = np.stack([2 * xi / ax, zero, eta / ax])
        dy = np.stack([zero, 2 * eta / ay, xi / ay])
        return basis, dx, dy

    def depth_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """z of the emitting layer at panel coordinates (mm)."""
        basis, _, _ = self._basis(x_mm, y_mm)
        return np.tensordot(self.params[:3], basis, axes=1)

    def trace(self, o: np.ndarray, q: np.ndarray, jacobian: bool = True
              ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Panel points Q (N, 2) mm of rays (origin o (N,3), slope q (N,2)) and dQ/d(o, q, s).

        Jacobians (when asked): "o" (N,2,3), "q" (N,2,2), "s" (N,2,4) for the screen
        parameters (only for mode "fit").
        """
        if self.mode == "flat":
            pts = o[:, :2] - o[:, 2:3] * q
            if not jacobian:
                return pts, {}
            n = len(o)
            jo = np.zeros((n, 2, 3))
            jo[:, 0, 0] = jo[:, 1, 1] = 1.0
            jo[:, :, 2] = -q
            jq = -o[:, 2, None, None] * np.eye(2)
            return pts, {"o": jo, "q": jq}
        h = float(self.params[3])
        n2 = float(self.glass_index) ** 2
        w = np.sqrt(n2 + (n2 - 1) * np.sum(q * q, axis=1))
        m = q / w[:, None]
        base = o[:, :2] - (h + o[:, 2:3]) * q
        pts = base + h * m
        for _ in range(_FIXED_POINT_ITERS):
            new = base + (self.depth_mm(pts[:, 0], pts[:, 1]) + h)[:, None] * m
            step = float(np.max(np.abs(new - pts), initial=0.0))
            pts = new
            if step < _FIXED_POINT_TOL_MM:
                break
        if not jacobian:
            return pts, {}
        basis, bdx, bdy = self._basis(pts[:, 0], pts[:, 1])
        c = np.tensordot(self.params[:3], basis, axes=1) + h
        grad = np.stack([self.params[:3] @ bdx, self.params[:3] @ bdy], axis=1)  # (N, 2)
        # A = (I - m g^T)^-1 = I + m g^T / (1 - g.m) (Sherman-Morrison).
        amat = np.eye(2) + m[:, :, None] * grad[:, None, :] / (1 - np.sum(grad * m, 1))[:, None,
                                                                                           None]
        mq = (np.eye(2) / w[:, None, None]
              - (n2 - 1) * q[:, :, None] * q[:, None, :] / (w**3)[:, None, None])
        jo = np.concatenate([amat, -(amat @ q[:, :, None])], axis=2)
        jq = amat @ (-(h + o[:, 2, None, None]) * np.eye(2) + c[:, None, None] * mq)
        js = np.empty((len(o), 2, 4))
        am = (amat @ m[:, :, None])[:, :, 0]  # (N, 2)
        js[:, :, :3] = am[:, :, None] * basis.T[:, None, :]
        js[:, :, 3] = (amat @ (m - q)[:, :, None])[:, :, 0]
        return pts, {"o": jo, "q": jq, "s": js}

    def to_json(self, std: np.ndarray | None = None) -> dict[str, object]:
        """The screen estimate for model.json stats (values and 1-sigma in mm)."""
        out: dict[str, object] = {"mode": self.mode, "glass_index": float(self.glass_index)}
        if self.mode == "fit":
            out.update({k: float(v) for k, v in zip(PARAM_NAMES, self.params, strict=True)})
            if std is not None:
                out["std"] = {k: float(v) for k, v in zip(PARAM_NAMES, std, strict=True)}
            out["gauge"] = ("shape terms with zero mean and tilt over the panel; the pose "
                            "places the emitting layer's mean plane; glass index fixed")
        return out
