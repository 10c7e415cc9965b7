"""Pose guidance for a rig of several cameras: the next screen pose that serves the rig.

Each camera is fitted on its own views as a single-camera session is (`fit_session`), which
gives its ray-sigma map and the screen's pose in each of its views. Views two cameras share
give their relative pose (the medoid of the per-view estimates, chained from the reference
camera as the joint fit's start is). Every candidate placement of every camera is carried
into every other camera: a camera is served by a candidate when the screen lands in its
image, and its worst ray sigma after the pose is predicted as for one camera.

How well the extrinsics are determined is counted by the views camera pairs share: a camera
that shares fewer than `MIN_SHARED_VIEWS` views with the others is tied weakly, and while one
is, only candidates it sees together with another camera are offered (a pose seen by one
camera alone adds nothing to the extrinsics). Otherwise the candidate that most lowers the
rig's worst predicted ray sigma (the worst over its cameras) wins.

The suggestion keeps, for each camera the pose serves, where that camera would see the
screen (its `Placement`: the corners an operator lines the screen up with on that camera's
preview), and each camera's ray-sigma map now, so a picture per camera can be drawn.
"""

from __future__ import annotations

import itertools
from collections import deque
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from calibration.fit.correspondences import PointSet, subsample
from calibration.guidance import MIN_GAIN, MIN_VISIBLE, NEAR_POSE_FRACTION, fit_session
from calibration.guidance_placement import (
    Placement,
    candidate_placements,
    outline_distance,
    place,
    planned_points,
    screen_centre_mm,
)
from calibration.models.base import CameraModel
from calibration.shared.plan import ScreenGeometry
from calibration.uncertainty import (
    RAY_SIGMA_GRID,
    RAY_SIGMA_POINTS_PER_POSE,
    covariance,
    direction_jacobian,
    free_parameters,
    pose_information,
    ray_sigma,
    reachable,
    sensor_grid,
    worst_ray_sigma,
)

MIN_SHARED_VIEWS = 3  # views a camera shares with the others before its extrinsics are tied
MIN_POINTS = 20  # samples of a camera's image the screen must cover to serve it
_SAMPLE_GRID = (32, 24)
Transform = tuple[np.ndarray, np.ndarray]  # (R, t): X_to = R @ X_from + t, mm


@dataclass
class CameraState:
    """One camera's own fit and what the prediction needs of it."""

    name: str
    model: CameraModel
    views: dict[str, Transform]  # view -> screen-to-camera pose of its own fit
    free: Any
    grid: np.ndarray
    jd: np.ndarray
    info: np.ndarray
    worst_before: float
    sigma_px: np.ndarray
    samples: np.ndarray
    rays: tuple[np.ndarray, np.ndarray]
    taken: list[np.ndarray]  # outlines of its views, camera px
    map_before: np.ndarray  # (ny, nx) ray sigma now, rad; nan beyond the reachable field

    def worst_after(self, rot: np.ndarray, t: np.ndarray, screen: ScreenGeometry
                    ) -> float | None:
        """The worst ray sigma after a screen pose (camera frame); None if not served."""
        pts = planned_points(self.rays, self.samples, screen, rot, t, self.sigma_px)
        if len(pts) < MIN_POINTS:
            return None
        w, h = self.model.image_size
        weight = min(RAY_SIGMA_POINTS_PER_POSE, len(pts) / len(self.samples) * w * h) / len(pts)
        after = ray_sigma(self.jd, covariance(
            self.info + weight * pose_information(self.model, rot, t, pts, self.free)))
        return float(worst_ray_sigma(self.model, self.grid, after))


def camera_state(name: str, points: dict[str, PointSet], image_size: tuple[int, int],
                 screen: ScreenGeometry, model_name: str) -> CameraState:
    """Fit one camera on its views (>= 3) and prepare its prediction."""
    if len(points) < 3:
        raise ValueError(f"camera {name}: guidance needs >= 3 decoded poses of every camera, "
                         f"{name} has {len(points)}")
    views = list(points)
    fit = fit_session([points[v] for v in views], image_size, screen, model_name)
    model = fit.model
    free = free_parameters(model, fit.param_std)
    grid = sensor_grid(model.image_size, *RAY_SIGMA_GRID)
    pts = [subsample(p, RAY_SIGMA_POINTS_PER_POSE) for p in fit.points]
    info = sum(pose_information(model, r, t, p, free)
               for (r, t), p in zip(fit.poses, pts, strict=True))
    jd = direction_jacobian(model, grid, free)
    before = ray_sigma(jd, covariance(info))
    samples = sensor_grid(model.image_size, *_SAMPLE_GRID)
    taken = [found.outline_px for r, t in fit.poses
             if (found := place(model, screen, r, t, 0.0)) is not None]
    reach = np.where(reachable(model, grid), 1.0, np.nan)
    return CameraState(name, model, dict(zip(views, fit.poses, strict=True)), free, grid, jd,
                       info, float(worst_ray_sigma(model, grid, before)),
                       np.nanmedian(np.concatenate([p.sigma_px for p in pts]), axis=0),
                       samples, model.unproject(samples), taken,
                       (before * reach).reshape(RAY_SIGMA_GRID[1], RAY_SIGMA_GRID[0]))


def shared_views(cameras: dict[str, CameraState]) -> dict[tuple[str, str], int]:
    """Views each camera pair shares (pairs in the cameras' order)."""
    return {(a, b): len(set(cameras[a].views) & set(cameras[b].views))
            for a, b in itertools.combinations(cameras, 2)}


def _medoid(estimates: list[Transform]) -> Transform:
    """The estimate nearest all others (rotation angle in rad plus translation over 100 mm)."""
    def gap(x: Transform, y: Transform) -> float:
        angle = float(np.linalg.norm(cv2.Rodrigues(x[0] @ y[0].T)[0]))
        return angle + float(np.linalg.norm(x[1] - y[1])) / 100.0
    return min(estimates, key=lambda e: sum(gap(e, o) for o in estimates))


def relative_poses(cameras: dict[str, CameraState], reference: str) -> dict[str, Transform]:
    """Each camera's pose from the reference camera's frame, chained through shared views;
    ValueError naming the cameras no shared view reaches."""
    placed: dict[str, Transform] = {reference: (np.eye(3), np.zeros(3))}
    queue = deque([reference])
    while queue:
        a = queue.popleft()
        for b, cam in cameras.items():
            common = set(cameras[a].views) & set(cam.views)
            if b in placed or not common:
                continue
            estimates = []
            for v in sorted(common):
                ra, ta = cameras[a].views[v]
                rb, tb = cam.views[v]
                rel = rb @ ra.T
                estimates.append((rel, tb - rel @ ta))
            rel, t_rel = _medoid(estimates)
            r0, t0 = placed[a]
            placed[b] = (rel @ r0, rel @ t0 + t_rel)
            queue.append(b)
    missing = [c for c in cameras if c not in placed]
    if missing:
        raise ValueError(f"cameras {', '.join(missing)} share no decoded pose with "
                         f"{reference} or a camera tied to it: capture a pose they see "
                         "together")
    return placed


@dataclass
class RigSuggestion:
    """The suggested screen pose (reference frame) and what it does for each camera."""

    rotation: np.ndarray
    translation: np.ndarray
    served: list[str]
    per_camera: list[dict[str, Any]]
    shared: dict[tuple[str, str], int]
    weak: list[str]
    worst_before_rad: float
    worst_after_rad: float
    helps: bool
    advice: str
    candidates: int
    rejected_repeats: int
    placements: dict[str, Placement]  # where each served camera sees the screen
    maps_before: dict[str, np.ndarray]  # camera -> (ny, nx) ray sigma now, rad
    image_sizes: dict[str, tuple[int, int]]  # camera -> (w, h)

    def to_json(self) -> dict[str, Any]:
        """JSON for the API: the pose for `screen_pose`, the cameras it serves with each
        camera's predicted worst sigma now and after and `outline_px` (the screen's corners
        in that camera's pixels, null where it does not serve), and the shared views per
        pair."""
        rvec = cv2.Rodrigues(self.rotation)[0].ravel()
        cameras = [{**c, "outline_px": np.round(self.placements[c["camera"]].outline_px, 2)
                    .tolist() if c["camera"] in self.placements else None}
                   for c in self.per_camera]
        return {
            "screen_pose": {"rvec": rvec.tolist(), "tvec_mm": self.translation.tolist()},
            "serves": self.served, "cameras": cameras,
            "shared_views": [{"cameras": [a, b], "views": n} for (a, b), n in
                             self.shared.items()],
            "weakly_tied": self.weak, "min_shared_views": MIN_SHARED_VIEWS,
            "predicted_worst_ray_sigma_urad": {"now": self.worst_before_rad * 1e6,
                                               "after": self.worst_after_rad * 1e6},
            "helps": self.helps, "advice": self.advice,
            "candidates_scored": self.candidates,
            "candidates_rejected_as_repeats": self.rejected_repeats,
        }


def _candidates(cameras: dict[str, CameraState], extr: dict[str, Transform],
                screen: ScreenGeometry, min_visible: float) -> list[Transform]:
    """Every camera's candidate placements, in the reference frame."""
    out = []
    for name, cam in cameras.items():
        dist0 = float(np.median([np.linalg.norm(r @ screen_centre_mm(screen) + t)
                                 for r, t in cam.views.values()]))
        r_c, t_c = extr[name]
        for placement, _, _ in candidate_placements(cam.model, screen, dist0,
                                                    min_visible=min_visible):
            out.append((r_c.T @ placement.rotation, r_c.T @ (placement.translation - t_c)))
    return out


def plan_rig_next_pose(points: dict[str, dict[str, PointSet]],
                       image_sizes: dict[str, tuple[int, int]], screen: ScreenGeometry,
                       reference: str, model_name: str = "opencv-rational",
                       min_visible: float = 1.0) -> RigSuggestion:
    """The next screen pose for a rig: `points` is camera -> view -> that camera's points of
    the view (views named alike are one screen pose seen by several cameras)."""
    if not MIN_VISIBLE <= min_visible <= 1.0:
        raise ValueError(f"min_screen_visible: expected {MIN_VISIBLE}..1, got {min_visible}")
    cameras = {c: camera_state(c, points[c], image_sizes[c], screen, model_name)
               for c in points}
    extr = relative_poses(cameras, reference)
    shared = shared_views(cameras)
    weak = [c for c in cameras if c != reference and
            sum(n for pair, n in shared.items() if c in pair) < MIN_SHARED_VIEWS]
    worst_before = max(c.worst_before for c in cameras.values())
    best: tuple[tuple[float, float], Transform, dict[str, float | None],
                dict[str, Placement]] | None = None
    scored = repeats = 0
    for rot, t in _candidates(cameras, extr, screen, min_visible):
        after: dict[str, float | None] = {}
        seen: dict[str, Placement] = {}
        near = []
        for name, cam in cameras.items():
            r_c, t_c = extr[name]
            rc, tc = r_c @ rot, r_c @ t + t_c
            found = place(cam.model, screen, rc, tc, 0.0)
            after[name] = cam.worst_after(rc, tc, screen) if found is not None else None
            if after[name] is not None:
                seen[name] = found
                near.append(any(outline_distance(found.outline_px, o, cam.model.image_size)
                                < NEAR_POSE_FRACTION for o in cam.taken))
        served = [c for c, v in after.items() if v is not None]
        if not served:
            continue
        if all(near):
            repeats += 1
            continue
        if weak and not (len(served) >= 2 and set(served) & set(weak)):
            continue
        scored += 1
        rig_worst = max(v if v is not None else cameras[c].worst_before
                        for c, v in after.items())
        total = sum(v if v is not None else cameras[c].worst_before for c, v in after.items())
        if best is None or (rig_worst, total) < best[0]:
            best = ((rig_worst, total), (rot, t), after, seen)
    if best is None:
        why = (f"no candidate pose is seen by {', '.join(weak)} together with another camera"
               if weak else "every candidate pose repeats poses already taken")
        raise ValueError(f"guidance: {why}; place the screen by hand where the cameras' "
                         "views overlap")
    (score, _), (rot, t), after, seen = best
    served = [c for c, v in after.items() if v is not None]
    helps = bool(weak) or score < (1 - MIN_GAIN) * worst_before
    if weak:
        advice = (f"capture this pose next: {', '.join(served)} see it together, which ties "
                  f"the extrinsics of {', '.join(sorted(set(weak) & set(served)))} (fewer "
                  f"than {MIN_SHARED_VIEWS} shared views so far)")
    elif helps:
        advice = (f"capture this pose next: the rig's worst predicted ray sigma would fall "
                  f"from {worst_before * 1e6:.3g} to {score * 1e6:.3g} urad")
    else:
        advice = (f"no pose tried lowers the rig's worst predicted ray sigma "
                  f"({worst_before * 1e6:.3g} urad) by {100 * MIN_GAIN:.0f} % or more: "
                  "calibrate the rig now")
    per_camera = [{"camera": c, "serves": after[c] is not None,
                   "predicted_worst_ray_sigma_urad": {
                       "now": cam.worst_before * 1e6,
                       "after": (after[c] if after[c] is not None else cam.worst_before) * 1e6},
                   "views": len(cam.views)} for c, cam in cameras.items()]
    return RigSuggestion(rot, t, served, per_camera, shared, weak, worst_before, score, helps,
                         advice, scored, repeats, seen,
                         {c: cam.map_before for c, cam in cameras.items()},
                         {c: cam.model.image_size for c, cam in cameras.items()})


__all__ = ["MIN_SHARED_VIEWS", "RigSuggestion", "plan_rig_next_pose", "relative_poses"]
