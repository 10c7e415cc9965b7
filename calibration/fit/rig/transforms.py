"""Rigid transforms as (R, t) pairs, X_to = R @ X_from + t, and their rotation vectors."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

Transform = tuple[np.ndarray, np.ndarray]


def from_rvec(rvec: np.ndarray) -> np.ndarray:
    """3x3 rotation of an axis-angle vector (rad, OpenCV's Rodrigues convention)."""
    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]


def to_rvec(rotation: np.ndarray) -> np.ndarray:
    """Axis-angle vector (3,) rad of a 3x3 rotation; exact for small angles too (OpenCV's
    Rodrigues returns zero below 1e-5 rad, more than a dense fit's rotation sigma)."""
    return Rotation.from_matrix(np.asarray(rotation, dtype=np.float64)).as_rotvec()


def compose(outer: Transform, inner: Transform) -> Transform:
    """outer after inner: X -> R_o (R_i X + t_i) + t_o."""
    return outer[0] @ inner[0], outer[0] @ inner[1] + outer[1]


def invert(tf: Transform) -> Transform:
    """The inverse transform."""
    return tf[0].T, -tf[0].T @ tf[1]


def mean_transform(transforms: list[Transform]) -> Transform:
    """A robust average: the member closest (rotation angle + translation) to all others.

    Used for start values only (the joint fit refines them), so the medoid is enough and
    keeps a single bad view from dragging the start away."""
    if len(transforms) == 1:
        return transforms[0]
    scale = max(float(np.median([np.linalg.norm(t) for _, t in transforms])), 1.0)
    costs = []
    for ra, ta in transforms:
        cost = 0.0
        for rb, tb in transforms:
            cost += (float(np.linalg.norm(to_rvec(ra.T @ rb)))
                     + float(np.linalg.norm(ta - tb)) / scale)
        costs.append(cost)
    return transforms[int(np.argmin(costs))]
