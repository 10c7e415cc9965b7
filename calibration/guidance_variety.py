"""Are a session's captured poses varied enough? A cheap check from their decoded maps, no fit.

Each pose is summarized by the homography from the screen to the image (a few hundred of
its decoded points: cheap enough for the server, no fit): the screen's four corners as the
camera saw them (its outline) and, with the camera's nominal pinhole, the screen's normal.
A pose whose outline lies within `DUPLICATE_FRACTION` of the image diagonal of an earlier
pose's repeats it (it adds almost nothing); the fits need poses whose screen normals
differ (parallel screens leave the focal length undetermined), at least
`MIN_NORMAL_SPREAD_DEG` apart.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from calibration.guidance_placement import Placement, outline_distance, screen_corners_mm
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import ScreenGeometry

DUPLICATE_FRACTION = 0.05  # outlines closer than this (of the image diagonal) repeat a pose
CAPTURED_FRACTION = 0.08  # a captured pose this close to a planned one has taken it
MIN_NORMAL_SPREAD_DEG = 10.0
_SIMILARITY_SCALE = 0.25  # outline distance (of the diagonal) at which similarity reaches 0
_HOMOGRAPHY_POINTS = 400
_MIN_POINTS = 20


@dataclass
class ObservedPose:
    """What the variety check keeps of a captured pose."""

    outline_px: np.ndarray  # (4, 2) the screen's corners as seen, corner (0, 0) first
    normal: np.ndarray  # (3,) the screen's normal in the camera frame, z > 0 (nominal K)
    valid_pixels: int

    def to_json(self) -> dict[str, Any]:
        """Plain lists (cached next to the pose's maps)."""
        return {"outline_px": self.outline_px.tolist(), "normal": self.normal.tolist(),
                "valid_pixels": self.valid_pixels}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ObservedPose:
        """Inverse of `to_json`."""
        return cls(np.asarray(data["outline_px"], float), np.asarray(data["normal"], float),
                   int(data["valid_pixels"]))


def observe(maps: DecodedMaps, screen: ScreenGeometry, camera_matrix: np.ndarray
            ) -> ObservedPose:
    """The pose's outline and screen normal from its decoded points (about
    `_HOMOGRAPHY_POINTS` valid pixels on an even grid; RANSAC drops decoding outliers);
    ValueError when it has too few valid points to tell."""
    valid = maps.mask & np.isfinite(maps.x) & np.isfinite(maps.y)
    stride = max(1, int(np.sqrt(max(int(valid.sum()), 1) / _HOMOGRAPHY_POINTS)))
    v, u = np.nonzero(valid[::stride, ::stride])
    v, u = v * stride, u * stride
    if len(u) < _MIN_POINTS:
        raise ValueError(f"pose has {len(u)} usable decoded points (need >= {_MIN_POINTS})")
    mm = np.stack([maps.x[v, u] * screen.pitch_mm[0], maps.y[v, u] * screen.pitch_mm[1]], 1)
    hom, _ = cv2.findHomography(mm, np.stack([u, v], 1).astype(np.float64), cv2.RANSAC, 3.0)
    if hom is None:
        raise ValueError("pose: its decoded points give no screen-to-image homography")
    corners = cv2.perspectiveTransform(screen_corners_mm(screen)[None, :, :2], hom)[0]
    m = np.linalg.solve(np.asarray(camera_matrix, float), hom)
    normal = np.cross(m[:, 0] / np.linalg.norm(m[:, 0]), m[:, 1] / np.linalg.norm(m[:, 1]))
    normal /= np.linalg.norm(normal)
    return ObservedPose(corners, normal if normal[2] > 0 else -normal, maps.valid_count())


def similarity(a: np.ndarray, b: np.ndarray, image_size: tuple[int, int]) -> float:
    """1 for the same outline, falling to 0 at a quarter of the image diagonal apart."""
    return max(0.0, 1.0 - outline_distance(a, b, image_size) / _SIMILARITY_SCALE)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(abs(float(a @ b)), -1.0, 1.0))))


def pose_variety(poses: list[tuple[str, ObservedPose]], image_size: tuple[int, int],
                 min_poses: dict[str, int]) -> dict[str, Any]:
    """`ready_for_guidance`, `ready_for_calibration` per model (`min_poses`: distinct poses
    each needs), `reason` in words and the `duplicates` (each pose that repeats an earlier
    one: `pose_id`, `repeats`, `similarity`)."""
    dup_sim = 1.0 - DUPLICATE_FRACTION / _SIMILARITY_SCALE
    duplicates, distinct = [], []
    for pid, pose in poses:
        match = max(((similarity(pose.outline_px, o.outline_px, image_size), oid)
                     for oid, o in distinct), default=None)
        if match is not None and match[0] >= dup_sim:
            duplicates.append({"pose_id": pid, "repeats": match[1],
                               "similarity": round(match[0], 3)})
        else:
            distinct.append((pid, pose))
    spread = max((_angle_deg(a.normal, b.normal) for i, (_, a) in enumerate(distinct)
                  for _, b in distinct[i + 1:]), default=0.0)
    tilted = spread >= MIN_NORMAL_SPREAD_DEG
    n = len(distinct)
    ready = {m: bool(n >= k and tilted) for m, k in sorted(min_poses.items())}
    guidance = bool(n >= 3 and tilted)
    reasons = []
    if duplicates:
        names = ", ".join(f"{d['pose_id']} repeats {d['repeats']}" for d in duplicates)
        reasons.append(f"{len(duplicates)} pose(s) repeat an earlier one ({names}): they add "
                       "almost nothing; move or tilt the screen before the next capture")
    if n < 3:
        reasons.append(f"{n} distinct pose(s): guidance and the fits need >= 3 distinct poses")
    if n >= 2 and not tilted:
        reasons.append(f"the screen's tilt varies by only {spread:.0f} deg between poses "
                       f"(need >= {MIN_NORMAL_SPREAD_DEG:.0f}): parallel screens leave the "
                       "focal length undetermined; tilt the screen 20-45 deg in different "
                       "directions")
    waiting = [m for m, ok in ready.items() if not ok]
    if guidance and waiting:
        reasons.append(f"{', '.join(waiting)} need(s) more distinct poses "
                       f"({', '.join(str(min_poses[m]) for m in waiting)})")
    if not reasons:
        reasons.append(f"{n} distinct poses, screen tilt varying by {spread:.0f} deg: ready")
    return {"ready_for_guidance": guidance, "ready_for_calibration": ready,
            "reason": "; ".join(reasons), "duplicates": duplicates,
            "distinct_poses": n, "tilt_spread_deg": round(spread, 1)}


def captured_by(planned: Placement, poses: list[tuple[str, ObservedPose]],
                image_size: tuple[int, int]) -> str | None:
    """The first captured pose whose outline matches a planned placement's, else None."""
    for pid, pose in poses:
        if outline_distance(planned.outline_px, pose.outline_px, image_size) < CAPTURED_FRACTION:
            return pid
    return None
