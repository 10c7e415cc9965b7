"""Find a board's corners in an image and turn them into one `phasecal.observations/1` view.

Chessboards go through `cv2.findChessboardCornersSB` (the classic
`cv2.findChessboardCorners` where it fails), then `cv2.cornerSubPix` (the whole board must be
seen: without markers a partial view has no unique corner
numbering); each corner's weight comes from OpenCV's edge-sharpness profiles around it
(a blurrier edge locates a corner less well). ChArUco boards go through
`cv2.aruco.CharucoDetector` (markers name the corners, so partial views count), with
sub-pixel corner refinement.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calibration.shared.observations import TargetObservations
from calibration.targets.board import TargetSpec

MIN_CHARUCO_CORNERS = 6  # a homography and some margin: fewer cannot fix a pose
WEIGHT_RANGE = (0.2, 5.0)  # sharpness weights are clipped here: one odd profile is not a vote
_SB_FLAGS = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)


class ImageError(ValueError):
    """An image file that cannot be read as a single-channel picture."""


@dataclass
class Detection:
    """What one image gave: a view, or the reason it gave none."""

    source: str
    observations: TargetObservations | None
    reason: str = ""


def read_gray(path: str | Path) -> np.ndarray:
    """An image file as 8-bit gray (16-bit images scaled down: the detectors take 8 bits)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        if not Path(path).is_file():
            raise ImageError(f"{path}: image file not found")
        raise ImageError(f"{path}: not an image OpenCV can read")
    return to_gray8(img, str(path))


def to_gray8(img: np.ndarray, source: str) -> np.ndarray:
    """Gray, 8-bit: colour is converted, 16-bit scaled by 1/257, float in [0, 1] by 255."""
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if img.ndim != 2:
        raise ImageError(f"{source}: expected a 2-D image, got shape {img.shape}")
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        return (img.astype(np.float64) / 257.0 + 0.5).astype(np.uint8)
    if img.dtype.kind == "f":
        return np.clip(np.nan_to_num(img) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    raise ImageError(f"{source}: unsupported pixel type {img.dtype}")


def corner_weights(gray: np.ndarray, spec: TargetSpec, corners: np.ndarray) -> np.ndarray:
    """Per-corner weight: the median edge transition width over the mean width of the edge
    profiles next to this corner (OpenCV's `estimateChessboardSharpness`)."""
    pattern = spec.corner_grid
    c32 = corners.reshape(-1, 1, 2).astype(np.float32)
    profiles = []
    for vertical in (False, True):
        _, sharp = cv2.estimateChessboardSharpness(gray, pattern, c32, 0.8, vertical)
        if sharp is not None and len(sharp):
            profiles.append(np.asarray(sharp, dtype=np.float64).reshape(-1, 5))
    if not profiles:
        return np.ones(len(corners))
    prof = np.concatenate(profiles)
    prof = prof[np.isfinite(prof[:, 2]) & (prof[:, 2] > 0)]
    if not len(prof):
        return np.ones(len(corners))
    spacing = _grid_spacing(corners, spec)
    dist = np.linalg.norm(corners[:, None, :] - prof[None, :, :2], axis=2)
    near = dist < 0.8 * spacing
    counts = near.sum(axis=1)
    local = np.where(counts > 0, (near * prof[None, :, 2]).sum(axis=1) / np.maximum(counts, 1),
                     np.median(prof[:, 2]))
    return np.clip(np.median(prof[:, 2]) / local, *WEIGHT_RANGE)


def _chessboard(gray: np.ndarray, spec: TargetSpec) -> tuple[np.ndarray | None, str]:
    """The corners and the detector that found them, or None and the reason."""
    pattern = (spec.cols, spec.rows)
    found, corners = cv2.findChessboardCornersSB(gray, pattern, _SB_FLAGS)
    if not found:  # the exhaustive search costs several times more: only when needed
        found, corners = cv2.findChessboardCornersSB(
            gray, pattern, _SB_FLAGS | cv2.CALIB_CB_EXHAUSTIVE)
    detector = "findChessboardCornersSB"
    if not found:
        # The classic detector finds some boards the sector-based one misses (strong
        # perspective, glare).
        detector = "findChessboardCorners"
        found, corners = cv2.findChessboardCorners(
            gray, pattern, cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        return None, (f"no complete {spec.cols}x{spec.rows} inner-corner chessboard found "
                      "(all corners must be in view)")
    return refine(gray, spec, corners.reshape(-1, 2)), detector + "+cornerSubPix"


def refine(gray: np.ndarray, spec: TargetSpec, corners: np.ndarray) -> np.ndarray:
    """Sub-pixel corners by `cv2.cornerSubPix` over a window of a quarter of the shortest
    corner spacing (wide enough to average the edges, short of the neighbouring corners)."""
    half = int(np.clip(round(0.25 * _grid_spacing(corners, spec, 5.0)), 2, 10))
    c32 = np.ascontiguousarray(corners, dtype=np.float32).reshape(-1, 1, 2)
    out = cv2.cornerSubPix(gray, c32, (half, half), (-1, -1), _SUBPIX_CRITERIA)
    return out.reshape(-1, 2).astype(np.float64)


def _cell_mean(gray: np.ndarray, quad: np.ndarray) -> float:
    """Mean gray level inside the middle of a cell given by its four corners."""
    centre = quad.mean(axis=0)
    inner = (centre + 0.5 * (quad - centre)).astype(np.int32)
    mask = np.zeros(gray.shape, np.uint8)
    cv2.fillConvexPoly(mask, inner, 1)
    return float(gray[mask > 0].mean()) if mask.any() else float("nan")


def canonical_order(gray: np.ndarray, spec: TargetSpec, corners: np.ndarray) -> np.ndarray:
    """Corners numbered so that the cell between corners 0, 1, COLS and COLS+1 is black
    (the detectors may start from either end). Only a board with COLS + ROWS odd tells its
    ends apart (its two end cells differ in colour); a symmetric one keeps the order found."""
    cols, rows = spec.corner_grid
    if (cols + rows) % 2 == 0:
        return corners
    grid = corners.reshape(rows, cols, 2)
    first = _cell_mean(gray, grid[[0, 0, 1, 1], [0, 1, 1, 0]])
    last = _cell_mean(gray, grid[[-1, -1, -2, -2], [-1, -2, -2, -1]])
    return corners[::-1].copy() if first > last else corners


def _grid_spacing(corners: np.ndarray, spec: TargetSpec, percentile: float = 50.0) -> float:
    """A percentile (default the median) of the distances (px) between neighbouring corners."""
    cols, rows = spec.corner_grid
    grid = corners.reshape(rows, cols, 2)
    return float(np.percentile(np.concatenate([
        np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel(),
        np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel()]), percentile))


def _charuco(gray: np.ndarray, spec: TargetSpec) -> tuple[np.ndarray | None, np.ndarray, str]:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.CharucoDetector(spec.charuco_board(), cv2.aruco.CharucoParameters(),
                                         params)
    corners, ids, _, marker_ids = detector.detectBoard(gray)
    n_markers = 0 if marker_ids is None else len(marker_ids)
    if corners is None or ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        got = 0 if ids is None else len(ids)
        return None, np.zeros(0, dtype=int), (
            f"{got} ChArUco corners from {n_markers} markers (need >= {MIN_CHARUCO_CORNERS})")
    return corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(int), ""


def detect_image(gray: np.ndarray, spec: TargetSpec, *, source: str = "image",
                 camera: str = "", view: str = "") -> Detection:
    """Detect `spec` in one 8-bit gray image: a view with every target point (NaN where not
    seen), or the reason there is none."""
    target = spec.points()
    xy = np.full((len(target), 2), np.nan)
    weight = np.ones(len(target))
    if spec.kind == "chessboard":
        corners, detector = _chessboard(gray, spec)
        if corners is None:
            return Detection(source, None, detector)
        xy[:] = canonical_order(gray, spec, corners)
        weight = corner_weights(gray, spec, corners)
    else:
        corners, ids, reason = _charuco(gray, spec)
        if corners is None:
            return Detection(source, None, reason)
        xy[ids] = corners
        detector = "CharucoDetector"
    h, w = gray.shape
    meta = {"target": spec.describe(), "camera": camera, "view": view or Path(source).stem,
            "source": source, "detector": detector,
            "corners_seen": int(np.isfinite(xy[:, 0]).sum())}
    obs = TargetObservations(xy, target, (w, h), weight=weight, meta=meta)
    obs.validate(source)
    return Detection(source, obs)


def detect_file(path: str | Path, spec: TargetSpec, *, camera: str = "") -> Detection:
    """`detect_image` on an image file; an unreadable file is a Detection with its reason."""
    try:
        gray = read_gray(path)
    except ImageError as exc:
        return Detection(str(path), None, str(exc).split(": ", 1)[-1])
    return detect_image(gray, spec, source=str(path), camera=camera)
