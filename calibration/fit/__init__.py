"""Estimators and optimizers that produce camera models from decoded maps.

Layout (imports only point down this list): `dispatch` (the one entry point) ->
families `classic/` (OpenCV parametric models and closed-form estimators), `raygrid/`,
`sgcc/` (raygrid starts from sgcc's initial poses) -> shared helpers `observations`,
`correspondences`, `heldout`, `result`, `ransac`.

The public interface is the names below (`from calibration.fit import DegenerateError,
rectangle_intrinsics, ...`); they load lazily, so importing one does not import them all.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    # errors and results
    "DegenerateError": "ransac",
    "NotPositiveDefiniteError": "classic.rotation",
    "CalibrationResult": "result",
    "PoseEstimate": "result",
    "IntrinsicsEstimate": "classic.estimate",
    # the full calibration
    "calibrate": "dispatch",
    # classic estimators: DLT, homographies, Zhang, PnP, RANSAC
    "ransac": "ransac",
    "fit_homography": "classic.homography",
    "ransac_homography": "classic.homography",
    "usac_homography": "classic.robust",
    "dlt_projection": "classic.dlt",
    "ransac_dlt": "classic.dlt",
    "decompose_projection": "classic.dlt",
    "zhang_intrinsics": "classic.zhang",
    "pose_from_homography": "classic.zhang",
    "solve_pnp": "classic.robust",
    "pnp_ransac": "classic.robust",
    "estimate_pose": "classic.pnp",
    # image lines and rectangles
    "fit_line": "classic.lines",
    "intersect": "classic.lines",
    "common_point": "classic.lines",
    "grid_vanishing_points": "classic.lines",
    "find_quads": "classic.quad",
    # quick intrinsics: rectangle vanishing points, general-motion and rotation-only
    "vanishing_points": "classic.rectangle",
    "rectangle_intrinsics": "classic.rectangle",
    "selfcal_intrinsics": "classic.selfcal",
    "interview_homographies": "classic.rotation",
    "rotation_intrinsics": "classic.rotation",
    # quick intrinsics from images or decoded poses
    "intrinsics_from_images": "classic.quick",
    "intrinsics_from_maps": "classic.quick",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    """Load a public name from its module on first use (PEP 562)."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'calibration.fit' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"calibration.fit.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
