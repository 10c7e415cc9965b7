"""Project target points through a parametric camera with OpenCV's analytic Jacobians.

One function, `project_view`, serves every pixel-space fit (one camera here, a rig in
calibration/fit/rig): pixels of target points seen from a pose (Rodrigues vector, mm),
with d(pixel)/d(pose), d(pixel)/d(intrinsics) in the model's `get_params()` order and
d(pixel)/d(target point), so a fit can also move the target's shape (a bowed board).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.models.parametric import PinholeFamily


@dataclass
class Projection:
    """Pixels of N target points and their derivatives (rows: u, v per point)."""

    pixels: np.ndarray  # (N, 2)
    d_pose: np.ndarray  # (N, 2, 6): rvec (3), tvec (3)
    d_intrinsics: np.ndarray  # (N, 2, P): fx, fy, cx, cy, distortion... (`get_params()`)
    d_point: np.ndarray  # (N, 2, 3): d pixel / d target point (target frame, mm)


def project_view(model: PinholeFamily, rvec: np.ndarray, tvec: np.ndarray,
                 target_xyz: np.ndarray) -> Projection:
    """Pixels of `target_xyz` (N, 3) mm seen from pose (rvec, tvec): X_cam = R X + t."""
    obj = np.ascontiguousarray(target_xyz, dtype=np.float64).reshape(-1, 1, 3)
    rv = np.asarray(rvec, dtype=np.float64).reshape(3, 1)
    tv = np.asarray(tvec, dtype=np.float64).reshape(3, 1)
    k, n = model.camera_matrix, obj.shape[0]
    if model.type_name == "fisheye":
        uv, jac = cv2.fisheye.projectPoints(obj, rv, tv, k, model.dist.reshape(4, 1))
        jac = jac.reshape(n, 2, 15)
        d_intr = jac[:, :, :8]  # fx, fy, cx, cy, k1..k4 (alpha, the skew, stays 0)
        d_pose = jac[:, :, 8:14]
    else:
        uv, jac = cv2.projectPoints(obj, rv, tv, k, model.dist)
        jac = jac.reshape(n, 2, -1)
        d_pose = jac[:, :, :6]
        d_intr = jac[:, :, 6:6 + 4 + model.n_dist]
    rot = cv2.Rodrigues(rv)[0]
    # d pixel / d X_cam is d pixel / d tvec; X_cam = R X + t, so d pixel / d X = that @ R.
    d_point = np.einsum("nij,jk->nik", d_pose[:, :, 3:], rot)
    return Projection(uv.reshape(n, 2), np.ascontiguousarray(d_pose),
                      np.ascontiguousarray(d_intr), d_point)
