"""Target observations (`phasecal.observations/1`): sparse correspondences between camera
pixels and points of a passive target (chessboard or ChArUco corners, surveyed points), one
NPZ per view. Shared by the detectors that write them, the fits that read them and the
service that stores uploads, so every reader applies the same checks."""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calibration.shared.atomic import atomic_file

OBSERVATIONS_FORMAT = "phasecal.observations/1"


class ObservationsError(ValueError):
    """An observations file or array set is malformed; the message names the key and why."""


@dataclass
class TargetObservations:
    """One view of a target: N target points (mm, target frame) and where the camera saw
    them (pixels; NaN rows where not seen)."""

    image_xy: np.ndarray  # float64 (N, 2), camera px (u, v)
    target_xyz: np.ndarray  # float64 (N, 3), mm
    image_size: tuple[int, int]  # (W, H)
    weight: np.ndarray | None = None  # float64 (N,): pixel sigma is sigma_px / weight
    sigma_px: float | None = None  # nominal pixel noise; None: estimated by the fit
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def count(self) -> int:
        """Number of target points (seen or not)."""
        return int(self.image_xy.shape[0])

    def used(self) -> np.ndarray:
        """Bool (N,): the points a fit uses (seen, finite, positive weight)."""
        ok = np.all(np.isfinite(self.image_xy), axis=1) & np.all(
            np.isfinite(self.target_xyz), axis=1)
        if self.weight is not None:
            ok &= np.isfinite(self.weight) & (self.weight > 0)
        return ok

    def used_count(self) -> int:
        """Number of points a fit uses."""
        return int(self.used().sum())

    def weights(self) -> np.ndarray:
        """Float64 (N,) relative weights (ones when the file has none)."""
        if self.weight is None:
            return np.ones(self.count)
        return np.asarray(self.weight, dtype=np.float64)

    def validate(self, source: str = "observations") -> None:
        """Check shapes, dtypes and values; raise `ObservationsError` naming the key."""
        xy, xyz = self.image_xy, self.target_xyz
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ObservationsError(
                f"{source}: image_xy: expected shape (N, 2), got {tuple(xy.shape)}")
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ObservationsError(
                f"{source}: target_xyz: expected shape (N, 3), got {tuple(xyz.shape)}")
        if xyz.shape[0] != xy.shape[0]:
            raise ObservationsError(
                f"{source}: target_xyz: {xyz.shape[0]} rows, image_xy has {xy.shape[0]}")
        if not np.all(np.isfinite(xyz)):
            raise ObservationsError(f"{source}: target_xyz: non-finite values")
        seen = ~np.any(np.isnan(xy), axis=1)
        if not np.all(np.isfinite(xy[seen])):
            raise ObservationsError(f"{source}: image_xy: infinite values (use NaN for unseen)")
        if self.weight is not None:
            w = self.weight
            if w.ndim != 1 or w.shape[0] != xy.shape[0]:
                raise ObservationsError(
                    f"{source}: weight: expected shape ({xy.shape[0]},), got {tuple(w.shape)}")
            if not np.all(np.isfinite(w)):
                raise ObservationsError(f"{source}: weight: non-finite values")
        if self.sigma_px is not None and not (np.isfinite(self.sigma_px) and self.sigma_px > 0):
            raise ObservationsError(
                f"{source}: sigma_px: expected a positive number, got {self.sigma_px}")
        w_img, h_img = self.image_size
        if w_img <= 0 or h_img <= 0:
            raise ObservationsError(
                f"{source}: image_size: expected positive (width, height), got {self.image_size}")
        fmt = self.meta.get("format", OBSERVATIONS_FORMAT)
        if fmt != OBSERVATIONS_FORMAT:
            raise ObservationsError(
                f"{source}: meta.format: expected {OBSERVATIONS_FORMAT!r}, got {fmt!r}")

    def npz_arrays(self) -> dict[str, np.ndarray]:
        """The NPZ members (docs/formats.md)."""
        arrays: dict[str, np.ndarray] = {
            "image_xy": np.asarray(self.image_xy, dtype=np.float64),
            "target_xyz": np.asarray(self.target_xyz, dtype=np.float64),
            "image_size": np.asarray(self.image_size, dtype=np.int64),
        }
        if self.weight is not None:
            arrays["weight"] = np.asarray(self.weight, dtype=np.float64)
        if self.sigma_px is not None:
            arrays["sigma_px"] = np.array(float(self.sigma_px))
        arrays["meta"] = np.array(json.dumps({**self.meta, "format": OBSERVATIONS_FORMAT}))
        return arrays

    def to_npz_bytes(self) -> bytes:
        """Serialize to NPZ bytes."""
        buf = io.BytesIO()
        np.savez_compressed(buf, **self.npz_arrays())
        return buf.getvalue()


def save_observations(obs: TargetObservations, path: str | Path) -> None:
    """Validate and write one view atomically (temp file, fsync, rename)."""
    obs.validate(str(path))
    with atomic_file(path) as fh:
        fh.write(obs.to_npz_bytes())


def _array(npz: Any, key: str, name: str) -> np.ndarray:
    try:
        return np.asarray(npz[key])
    except ValueError as exc:  # object arrays refused by allow_pickle=False
        raise ObservationsError(f"{name}: {key}: not a plain numeric array ({exc})") from None


def _numeric(arr: np.ndarray, key: str, name: str) -> np.ndarray:
    if arr.dtype.kind not in "fiu":
        raise ObservationsError(f"{name}: {key}: expected numbers, got dtype {arr.dtype}")
    return arr.astype(np.float64)


def load_observations(source: str | Path | bytes) -> TargetObservations:
    """Read and validate a `phasecal.observations/1` NPZ (path or bytes)."""
    name = "<bytes>" if isinstance(source, bytes) else str(source)
    try:
        data = source if isinstance(source, bytes) else Path(source).read_bytes()
    except FileNotFoundError:
        raise ObservationsError(f"{name}: observations file not found") from None
    except OSError as exc:
        raise ObservationsError(f"{name}: cannot read ({exc.strerror})") from None
    if data[:4] != b"PK\x03\x04":
        raise ObservationsError(f"{name}: not an NPZ file (expected a zip archive of .npy arrays)")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            keys = set(npz.files)
            missing = [k for k in ("image_xy", "target_xyz", "image_size", "meta")
                       if k not in keys]
            if missing:
                raise ObservationsError(
                    f"{name}: not a {OBSERVATIONS_FORMAT} file, missing keys {missing}")
            try:
                meta = json.loads(str(_array(npz, "meta", name)))
            except json.JSONDecodeError:
                raise ObservationsError(f"{name}: meta: not valid JSON") from None
            if not isinstance(meta, dict):
                raise ObservationsError(f"{name}: meta: expected a JSON object")
            if meta.get("format") != OBSERVATIONS_FORMAT:
                raise ObservationsError(f"{name}: meta.format: expected "
                                        f"{OBSERVATIONS_FORMAT!r}, got {meta.get('format')!r}")
            size = _array(npz, "image_size", name)
            if size.shape != (2,) or size.dtype.kind not in "iu":
                raise ObservationsError(f"{name}: image_size: expected 2 integers (width, "
                                        f"height), got {size.dtype} {tuple(size.shape)}")
            weight = _numeric(_array(npz, "weight", name), "weight", name) \
                if "weight" in keys else None
            sigma = None
            if "sigma_px" in keys:
                s = _numeric(_array(npz, "sigma_px", name), "sigma_px", name)
                if s.shape != ():
                    raise ObservationsError(
                        f"{name}: sigma_px: expected a 0-d number, got shape {tuple(s.shape)}")
                sigma = float(s)
            obs = TargetObservations(
                image_xy=_numeric(_array(npz, "image_xy", name), "image_xy", name),
                target_xyz=_numeric(_array(npz, "target_xyz", name), "target_xyz", name),
                image_size=(int(size[0]), int(size[1])),
                weight=weight, sigma_px=sigma, meta=meta)
    except ObservationsError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ObservationsError(f"{name}: not a readable NPZ file ({exc})") from None
    obs.validate(name)
    return obs
