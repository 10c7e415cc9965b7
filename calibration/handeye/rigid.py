"""Rigid transforms with the perturbation every hand-eye covariance is stated in: a 6-vector
(rotation vector w in rad, translation d in mm) moves (R, t) to (expm(w) R, t + d)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Rigid:
    """X_to = rotation @ X_from + translation (mm)."""

    rotation: np.ndarray
    translation: np.ndarray

    @classmethod
    def identity(cls) -> Rigid:
        return cls(np.eye(3), np.zeros(3))

    def __matmul__(self, other: Rigid) -> Rigid:
        return Rigid(self.rotation @ other.rotation,
                     self.rotation @ other.translation + self.translation)

    def inverse(self) -> Rigid:
        return Rigid(self.rotation.T, -self.rotation.T @ self.translation)

    def perturbed(self, delta: np.ndarray) -> Rigid:
        """(expm(w) R, t + d) for delta = (w, d)."""
        return Rigid(Rotation.from_rotvec(delta[:3]).as_matrix() @ self.rotation,
                     self.translation + delta[3:])

    def minus(self, other: Rigid) -> np.ndarray:
        """The delta with other.perturbed(delta) == self."""
        w = Rotation.from_matrix(self.rotation @ other.rotation.T).as_rotvec()
        return np.concatenate([w, self.translation - other.translation])

    def to_json(self, covariance: np.ndarray | None = None) -> dict[str, Any]:
        out: dict[str, Any] = {"R": self.rotation.tolist(), "t_mm": self.translation.tolist()}
        if covariance is not None:
            out["covariance"] = np.asarray(covariance).tolist()
        return out


def batch_matrices(rotvecs: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors -> (N, 3, 3) matrices."""
    return Rotation.from_rotvec(rotvecs).as_matrix()


def batch_rotvecs(matrices: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices -> (N, 3) rotation vectors."""
    return Rotation.from_matrix(matrices).as_rotvec()


def mean_rigid(transforms: list[Rigid]) -> Rigid:
    """The chordal mean rotation and the mean translation of several estimates of one
    transform (what the classical methods' per-view estimates of the other transform are
    averaged with)."""
    rot = Rotation.from_matrix(np.stack([t.rotation for t in transforms])).mean().as_matrix()
    return Rigid(rot, np.mean([t.translation for t in transforms], axis=0))
