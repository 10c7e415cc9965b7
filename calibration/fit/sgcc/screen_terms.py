"""The fitted screen of sGCC (`screen: "fit"`): its ray terms, gauge and statistics.

Rays are traced to the bowed panel behind cover glass by `ScreenTrace`
(calibration/metrology/screen_trace.py), the tracer of the parametric fits' `ScreenModel`
too, so both fits share the physics and the parameters (docs/physics.md section 8). Here that
trace is chained to sGCC's spline components and poses, feature-major ((k, n) arrays) and on
any array module, for the threaded CPU path (sgcc/problem.py) and the GPU path
(sgcc/device.py) alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from types import ModuleType
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from calibration.metrology.screen import ScreenModel
from calibration.metrology.screen_trace import N_SCREEN, ScreenTrace
from calibration.models.sgcc import expmap_jacobian_rows, expmap_rows
from calibration.shared.plan import ScreenGeometry


def _cross(a: Any, b: Any) -> Any:
    """Cross products of feature-major 3-vectors (3,n) x (3,n), on any array module."""
    return a[[1, 2, 0]] * b[[2, 0, 1]] - a[[2, 0, 1]] * b[[1, 2, 0]]


def rays_in_screen_frame(xp: ModuleType, comps: Any, rc: Any, tc: Any, jacobian: bool
                         ) -> tuple[Any, Any, Any, Any, Any]:
    """The rays of spline components comps (C,n) in the screen frame of pose (rc, tc):
    (d r/d(comps[:2]) (3,2,n) or None, directions r_s (3,n), origins o_s (3,n), ok (n,): the
    ray moves towards the screen, r_z (n,) with 1 where not ok)."""
    if jacobian:
        r, jr = expmap_jacobian_rows(comps[0], comps[1], xp=xp)
    else:
        r, jr = expmap_rows(comps[0], comps[1], xp=xp), None
    r_s = rc @ r
    o_s = (rc[:, :2] @ comps[2:4] + tc[:, None] if len(comps) == 4
           else xp.broadcast_to(tc[:, None], r.shape))
    ok = r_s[2] * o_s[2] < 0
    return jr, r_s, o_s, ok, xp.where(ok, r_s[2], 1.0)


def panel_ray_terms(
    xp: ModuleType, comps: Any, rc: Any, tc: Any, screen: Any, jacobian: bool,
    panel: tuple[ScreenTrace, Any],
) -> tuple[Any, ...]:
    """`problem.ray_terms` through the fitted screen (sgcc/screen_terms.py): the ray in the screen
    frame is traced through the cover glass to the shaped panel; J has 4 screen columns."""
    c = len(comps)
    jr, r_s, o_s, ok, rz = rays_in_screen_frame(xp, comps, rc, tc, jacobian)
    slope = r_s[:2] / rz
    if not jacobian:
        q = panel[0].points(xp, panel[1], o_s, xp.where(ok, slope, 0.0))
        return xp.where(ok, q - screen, 0.0), ok
    q, jo, jq, js = panel[0].trace(xp, panel[1], o_s, xp.where(ok, slope, 0.0))
    res = xp.where(ok, q - screen, 0.0)
    # dQ/d(r_s) = dQ/dq dq/d(r_s), dq/d(r_s) = [[1, 0, -qx], [0, 1, -qy]] / r_z.
    jr_s = xp.empty((2, 3, len(rz)))
    jr_s[:, 0], jr_s[:, 1] = jq[:, 0] / rz, jq[:, 1] / rz
    jr_s[:, 2] = -(jq[:, 0] * slope[0] + jq[:, 1] * slope[1]) / rz
    mrc = xp.tensordot(rc, jr_s, axes=([0], [1])).transpose(1, 0, 2)  # (2,3,n): dQ/dr_s Rc
    g = xp.empty((2, c, len(rz)))
    g[:, :2] = (mrc[:, :, None, :] * jr[None]).sum(axis=1)
    if c == 4:
        g[:, 2:] = xp.tensordot(rc[:, :2], jo, axes=([0], [1])).transpose(1, 0, 2)
    jp = xp.empty((2, 6 + N_SCREEN, len(rz)))
    for i in range(2):  # d/d(omega) = -(dQ/do_s [o_s]x + dQ/dr_s [r_s]x), row-wise o x row
        jp[i, :3] = _cross(o_s, jo[i]) + _cross(r_s, jr_s[i])
    jp[:, 3:6] = jo
    jp[:, 6:] = js
    return res, ok, g, jp


# sgcc-noncentral: below this spread of the screen normals between poses the glass thickness
# is a gauge freedom (held at 0); above it the stds are honest; a warning names poor ones.
MIN_NORMAL_SPREAD_DEG = 2.0
POOR_STD_MM = 0.1

GAUGE = ("shape terms with zero mean and tilt over the panel (a plane of the panel is the "
         "pose's); the pose places the emitting layer's mean plane; glass index fixed (index "
         "and thickness trade). The paraxial part of the glass, a shift of the apparent panel by "
         "h(1 - 1/n) along its normal, is the pose's distance: h is determined by the angle "
         "dependence of the refraction")
GAUGE_NONCENTRAL = ("; sgcc-noncentral: the glass's lateral shift depends only on the angle "
                    "between ray and screen normal, so when every pose has the same normal in "
                    "the camera frame the per-pixel ray offsets absorb it exactly and h is a "
                    "gauge freedom (held at 0 below a normal spread of "
                    f"{MIN_NORMAL_SPREAD_DEG:g} degrees); otherwise h and the bow come from the "
                    "spread of normals and distances between poses, and their std says how well")


def normal_spread_deg(rvecs: Sequence[np.ndarray]) -> float:
    """Largest angle (degrees) between two poses' screen normals in the camera frame, from the
    poses' rotation vectors (screen -> camera, OpenCV's rvecs)."""
    normals = np.array([Rotation.from_rotvec(np.ravel(r)).as_matrix()[:, 2] for r in rvecs])
    cos = np.clip(normals @ normals.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


def holds_glass(n_comp: int, spread_deg: float) -> bool:
    """Whether the glass thickness is a gauge freedom: non-central, one screen normal."""
    return n_comp == 4 and spread_deg < MIN_NORMAL_SPREAD_DEG


def screen_stats(geometry: ScreenGeometry, mode: str, index: float, params: np.ndarray | None,
                 covariance: np.ndarray, n_comp: int, spread_deg: float, held: bool
                 ) -> dict[str, object]:
    """`stats.screen` as the parametric families report it: mode, index, and for "fit" the
    estimates with their 1-sigma (mm, the last 4 rows of the fit's covariance) and the gauge;
    plus the screen normals' spread between poses and whether the glass was held."""
    if mode != "fit" or params is None:
        return ScreenModel(geometry, "flat", index).to_json()
    std = np.sqrt(np.maximum(np.diag(covariance)[-N_SCREEN:], 0.0))
    out = ScreenModel(geometry, "fit", index, params).to_json(std)
    out["gauge"] = GAUGE + (GAUGE_NONCENTRAL if n_comp == 4 else "")
    out["normal_spread_deg"] = spread_deg
    out["glass_held"] = held
    return out


def screen_warnings(stats: dict[str, object]) -> list[str]:
    """Plain-language findings about a fitted screen for the CLI and reports."""
    if stats.get("mode") != "fit":
        return []
    if stats["glass_held"]:
        return [f"every pose shows the screen with the same normal (spread "
                f"{stats['normal_spread_deg']:.2g} degrees): the cover glass cannot be told from "
                "the non-central ray offsets, so its thickness is held at 0 and the rays include "
                "its shift; add poses tilted by 15 degrees or more against each other"]
    std = stats["std"]  # type: ignore[index]
    poor = [f"{k} +-{v:.2g} mm" for k, v in std.items() if v > POOR_STD_MM]  # type: ignore[union-attr]
    if poor:
        return [f"the screen is poorly determined ({', '.join(poor)}): add poses whose screen "
                "normals differ by 15 degrees or more, at several distances"]
    return []
