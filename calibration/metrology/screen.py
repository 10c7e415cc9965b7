"""The screen model of the fits: flat and bare, or a shaped panel behind cover glass.

`ScreenModel` holds what a fit estimates and reports (mode, glass index, parameters
[bow_x, bow_y, twist, glass] mm) and serializes it; with `screen: "fit"` it traces rays with
`ScreenTrace` (calibration/metrology/screen_trace.py: bow, twist and the refraction at the
cover glass, docs/physics.md section 8), the same code sGCC fits with. Gauge: the shape terms
have zero mean and zero tilt over the panel, so no plane of it trades with the pose; the pose
places the emitting layer's mean plane.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.metrology.screen_trace import ScreenTrace
from calibration.shared.plan import ScreenGeometry

SCREEN_MODES = ("flat", "fit")
PARAM_NAMES = ("bow_x_mm", "bow_y_mm", "twist_mm", "glass_mm")


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

    @property
    def tracer(self) -> ScreenTrace:
        """The shared tracer of this panel and glass (calibration/metrology/screen_trace.py)."""
        return ScreenTrace.of(self.geometry, self.glass_index)

    def depth_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """z of the emitting layer at panel coordinates (mm)."""
        return self.tracer.depth(self.params, x_mm, y_mm)[2]

    def trace(self, o: np.ndarray, q: np.ndarray, jacobian: bool = True
              ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Panel points Q (N, 2) mm of rays (origin o (N,3), slope q (N,2)) and dQ/d(o, q, s).

        Jacobians (when asked): "o" (N,2,3), "q" (N,2,2), "s" (N,2,4) for the screen
        parameters (only for mode "fit"). Pixel-major views of `ScreenTrace`'s feature-major
        results (the same numbers as sGCC's).
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
        if not jacobian:
            return self.tracer.points(np, self.params, o.T, q.T).T, {}
        pts, jo, jq, js = self.tracer.trace(np, self.params, o.T, q.T)
        return pts.T, {"o": jo.transpose(2, 0, 1), "q": jq.transpose(2, 0, 1),
                       "s": js.transpose(2, 0, 1)}

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
