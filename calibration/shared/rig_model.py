"""The rig model (`phasecal.rig/1`): each camera's model with its pose in the reference
camera's frame and that pose's covariance. Shared by the joint fit that writes it, the
commands and routes that evaluate and export it, so every reader applies the same checks.

Extrinsics map the reference camera's frame into the camera's: X_cam = R @ X_ref + t (mm);
the covariance is 6x6 over (rotation vector rad, t mm); the reference camera has identity
and zeros.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calibration.models.base import CameraModel, ModelError, jsonable, model_from_dict
from calibration.shared.atomic import write_text_atomic

RIG_FORMAT = "phasecal.rig/1"


class RigModelError(ModelError):
    """A rig file is malformed; the message names the field."""


@dataclass
class RigCamera:
    """One camera of a rig: its model and reference-to-camera extrinsics with covariance."""

    model: CameraModel
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,) mm
    covariance: np.ndarray  # (6, 6) over (rotation vector rad, t mm)

    def sigma(self) -> dict[str, float]:
        """1-sigma of the extrinsics: rotation (largest axis, mrad) and translation (mm)."""
        d = np.sqrt(np.clip(np.diag(self.covariance), 0, None))
        return {"rotation_mrad": float(np.linalg.norm(d[:3]) * 1e3),
                "translation_mm": float(np.linalg.norm(d[3:]))}

    def to_reference(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) -> reference frame."""
        return (np.asarray(points, dtype=np.float64) - self.translation) @ self.rotation

    def from_reference(self, points: np.ndarray) -> np.ndarray:
        """Reference-frame points (N, 3) -> camera frame."""
        return np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    def unproject(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels -> rays (origins mm, unit directions) in the reference camera's frame."""
        o, d = self.model.unproject(pixels)
        return self.to_reference(o), np.asarray(d, dtype=np.float64) @ self.rotation

    def project(self, points: np.ndarray) -> np.ndarray:
        """Reference-frame points (N, 3) mm -> this camera's pixels (NaN where not seen)."""
        return self.model.project(self.from_reference(points))


@dataclass
class RigModel:
    """Several cameras in one frame: the reference camera's."""

    reference: str
    cameras: dict[str, RigCamera]
    stats: dict[str, Any] = field(default_factory=dict)

    def camera(self, name: str) -> RigCamera:
        """The camera called `name`; RigModelError listing the rig's cameras otherwise."""
        if name not in self.cameras:
            raise RigModelError(f"camera: expected one of {sorted(self.cameras)}, got {name!r}")
        return self.cameras[name]

    def relative(self, first: str, second: str) -> tuple[np.ndarray, np.ndarray]:
        """(R, T) with X_second = R @ X_first + T (cv2.stereoCalibrate's convention)."""
        a, b = self.camera(first), self.camera(second)
        rot = b.rotation @ a.rotation.T
        return rot, b.translation - rot @ a.translation

    def to_dict(self) -> dict[str, Any]:
        """The whole `phasecal.rig/1` document."""
        return {
            "format": RIG_FORMAT,
            "reference": self.reference,
            "cameras": {name: {"model": cam.model.to_dict(),
                               "extrinsics": {"R": cam.rotation.tolist(),
                                              "t_mm": cam.translation.tolist(),
                                              "covariance": cam.covariance.tolist()}}
                        for name, cam in self.cameras.items()},
            "stats": jsonable(self.stats),
        }


def _matrix(value: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
    """A finite numeric array of `shape` from JSON lists, or RigModelError naming `where`."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RigModelError(f"{where}: expected numbers of shape {list(shape)}") from None
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise RigModelError(f"{where}: expected finite numbers of shape {list(shape)}, got "
                            f"shape {list(arr.shape)}")
    return arr


def _camera_from_dict(name: str, data: Any, source: str) -> RigCamera:
    where = f"{source}: cameras.{name}"
    if not isinstance(data, dict) or "model" not in data or "extrinsics" not in data:
        raise RigModelError(f"{where}: expected an object with model and extrinsics")
    try:
        model = model_from_dict(data["model"], source=f"{where}.model")
    except ModelError as exc:
        raise RigModelError(str(exc)) from None
    ext = data["extrinsics"]
    if not isinstance(ext, dict):
        raise RigModelError(f"{where}.extrinsics: expected an object with R, t_mm, covariance")
    rot = _matrix(ext.get("R"), (3, 3), f"{where}.extrinsics.R")
    if not (np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) and np.linalg.det(rot) > 0):
        raise RigModelError(f"{where}.extrinsics.R: not a proper rotation matrix")
    t = _matrix(ext.get("t_mm"), (3,), f"{where}.extrinsics.t_mm")
    cov = _matrix(ext.get("covariance"), (6, 6), f"{where}.extrinsics.covariance")
    if not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-12 * max(float(np.abs(cov).max()), 1e-300)):
        raise RigModelError(f"{where}.extrinsics.covariance: not symmetric")
    if np.any(np.diag(cov) < 0):
        raise RigModelError(f"{where}.extrinsics.covariance: negative variance on the diagonal")
    # A rotation stored to JSON precision: the nearest rotation matrix (SVD). Not through
    # cv2.Rodrigues, which returns a zero vector below 1e-5 rad: a dense fit's sigma is
    # smaller than that, and a near-parallel pair's rotation became exactly identity.
    u, _, vt = np.linalg.svd(rot)
    rot = u @ vt
    return RigCamera(model, rot, t, cov)


def rig_from_dict(data: Any, source: str = "rig") -> RigModel:
    """Validate a `phasecal.rig/1` document and build the rig."""
    if not isinstance(data, dict):
        raise RigModelError(f"{source}: expected a JSON object, got {type(data).__name__}")
    if data.get("format") != RIG_FORMAT:
        raise RigModelError(f"{source}: format: expected {RIG_FORMAT!r}, got "
                            f"{data.get('format')!r}")
    if "reference" not in data and ("display" in data or "kind" in data):
        raise RigModelError(f"{source}: an acquisition rig config (devices and settings), not "
                            "a calibrated rig model (reference, cameras with extrinsics)")
    cams = data.get("cameras")
    if not isinstance(cams, dict) or len(cams) < 2:
        raise RigModelError(f"{source}: cameras: expected an object with >= 2 cameras")
    cameras = {str(n): _camera_from_dict(str(n), c, source) for n, c in cams.items()}
    ref = data.get("reference")
    if ref not in cameras:
        raise RigModelError(f"{source}: reference: expected one of {sorted(cameras)}, got {ref!r}")
    r = cameras[ref]
    if not (np.allclose(r.rotation, np.eye(3), atol=1e-9) and np.allclose(r.translation, 0)
            and np.allclose(r.covariance, 0)):
        raise RigModelError(f"{source}: cameras.{ref}.extrinsics: the reference camera must "
                            "have R = identity, t = 0 and a zero covariance")
    stats = data.get("stats", {})
    return RigModel(str(ref), cameras, stats if isinstance(stats, dict) else {})


def is_rig_document(data: Any) -> bool:
    """Whether parsed JSON claims to be a rig model (then `rig_from_dict` checks it). The
    acquisition rig config carries the same format string; it has no `reference`."""
    return isinstance(data, dict) and data.get("format") == RIG_FORMAT and "reference" in data


def load_rig(path: str | Path) -> RigModel:
    """Read and validate a rig JSON file."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RigModelError(f"{p}: rig file not found") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RigModelError(f"{p}: not valid JSON ({exc})") from None
    return rig_from_dict(data, source=str(p))


def save_rig(rig: RigModel, path: str | Path) -> None:
    """Write a rig JSON file atomically (validated by reading its own document back)."""
    doc = rig.to_dict()
    rig_from_dict(json.loads(json.dumps(doc)), source=str(path))
    write_text_atomic(path, json.dumps(doc, indent=1) + "\n")
