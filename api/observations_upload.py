"""Validate an uploaded view of a target session before anything is stored: an observations
NPZ (`phasecal.observations/1`: members and expanded size checked before any array is read,
then the format's own checks, then the session's board), or an image the session's board
is detected in."""

from __future__ import annotations

import io
import zipfile

import cv2
import numpy as np

from api.problems import Problem
from calibration import TargetSpec, detect_image
from calibration.shared.observations import (
    ObservationsError,
    TargetObservations,
    load_observations,
)

MEMBERS = {f"{k}.npy" for k in ("image_xy", "target_xyz", "weight", "sigma_px", "image_size",
                                 "meta")}
POINTS_TARGET = "points"  # a session of surveyed points: observation files only
BOARD_TOLERANCE_MM = 1e-6  # uploaded target points must be the session's board's


def _bad(name: str, detail: str) -> Problem:
    return Problem(422, "invalid-observations", f"{name}: {detail}")


def _check_archive(data: bytes, name: str, max_bytes: int) -> None:
    """Members and expanded size of an NPZ, without decompressing any array."""
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, ValueError) as exc:
        raise _bad(name, f"not a phasecal.observations/1 NPZ file: {exc}") from None
    with zf:
        infos = zf.infolist()
        total = sum(i.file_size for i in infos)
        if total > max_bytes:
            raise Problem(413, "too-large", f"{name}: the archive expands to {total} bytes, "
                          f"over the upload limit of {max_bytes} bytes")
        unknown = sorted(i.filename for i in infos if i.filename not in MEMBERS)
        if unknown:
            raise _bad(name, f"unexpected members {unknown} (expected {sorted(MEMBERS)})")


def _check_board(obs: TargetObservations, spec: TargetSpec, name: str) -> None:
    """An uploaded view of a board session must number the board's points as it does."""
    want = spec.points()
    if obs.target_xyz.shape != want.shape or not np.allclose(
            obs.target_xyz, want, atol=BOARD_TOLERANCE_MM, rtol=0):
        raise _bad(name, f"target_xyz: not the points of the session's board "
                   f"{spec.describe()} ({want.shape[0]} points in OpenCV's order)")


def observations_from_upload(data: bytes, name: str, target: str, max_bytes: int
                             ) -> tuple[TargetObservations, str]:
    """(the view, its source "observations" or "image") from an uploaded file; 413 or 422
    problems naming the file and what is wrong."""
    spec = None if target == POINTS_TARGET else TargetSpec.parse(target)
    if data[:4] == b"PK\x03\x04":
        _check_archive(data, name, max_bytes)
        try:
            obs = load_observations(data)
        except ObservationsError as exc:
            raise _bad(name, str(exc).removeprefix("<bytes>: ")) from None
        if spec is not None:
            _check_board(obs, spec, name)
        obs.meta.setdefault("source", name)
        return obs, "observations"
    if spec is None:
        raise _bad(name, "a session of surveyed points takes observation files "
                   "(phasecal.observations/1 NPZ), not images")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise _bad(name, "neither an observations NPZ nor an image OpenCV can read")
    found = detect_image(img, spec, source=name)
    if found.observations is None:
        raise Problem(422, "nothing-detected", f"{name}: {found.reason}")
    return found.observations, "image"
