"""Pose guidance: which screen pose to capture next to shrink the worst ray uncertainty.

The session's poses are fitted with the same weighted fit a calibration of that model runs
(`fit_parametric_dense` with the model's default options), so the predicted figures are the
ones the calibration's report will show: the ray-sigma map and its worst value come from
`calibration.uncertainty` (`ray_sigma_map`, `worst_ray_sigma`), the one definition both use.

The information each candidate placement (`calibration.guidance_placement`) would add is
predicted without capturing it: the image is sampled on an even grid, each sample's ray is
intersected with the candidate screen plane and kept if it lands on the screen, and those
points (with the session's median decoded sigma, counted as the report counts a real pose's
points) are added to the normal equations. Candidates that repeat a pose already taken
(their outline within `NEAR_POSE_FRACTION` of the image diagonal of a fitted pose's
outline) are not offered; the candidate with the smallest worst predicted ray sigma wins,
and when none lowers it by `MIN_GAIN` the answer says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.fit.correspondences import PointSet, point_set, subsample
from calibration.fit.registry import PARAMETRIC
from calibration.guidance_placement import (
    DEFAULT_MIN_VISIBLE,
    Placement,
    candidate_placements,
    outline_distance,
    place,
    planned_points,
    screen_centre_mm,
)
from calibration.metrology.refine import fit_parametric_dense
from calibration.models.base import CameraModel
from calibration.shared.maps import DecodedMaps
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

MIN_VISIBLE = 0.5  # the least part of a suggested screen inside the image one may ask for
NEAR_POSE_FRACTION = 0.05  # outlines this close (of the image diagonal) repeat a pose
MIN_GAIN = 0.02  # a suggestion must lower the worst predicted sigma by this fraction
_SAMPLE_GRID = (32, 24)  # image samples per candidate


@dataclass
class SessionFit:
    """A parametric fit of a session's poses, as a calibration of that model would make it."""

    model: CameraModel
    poses: list[tuple[np.ndarray, np.ndarray]]  # (R, t) per pose
    points: list[PointSet]  # per pose (counted with at most RAY_SIGMA_POINTS_PER_POSE)
    param_std: dict[str, float] | None
    note: str = ""  # the fit's own note (a rational fit refitted away from 0/0)


@dataclass
class Suggestion:
    """A suggested next screen pose and what it is predicted to achieve."""

    placement: Placement
    tilt_deg: float
    tilt_azimuth_deg: float
    worst_before_rad: float
    worst_after_rad: float
    candidates: int
    rejected_repeats: int
    helps: bool
    advice: str
    map_before: np.ndarray  # (ny, nx) rad, nan beyond the reachable field
    map_after: np.ndarray  # (ny, nx) rad
    image_size: tuple[int, int]
    region_fraction: float
    note: str  # about the fit the prediction rests on ('' when nothing to say)

    @property
    def rotation(self) -> np.ndarray:
        """The suggested screen rotation (screen -> camera)."""
        return self.placement.rotation

    @property
    def translation(self) -> np.ndarray:
        """The suggested screen translation (mm)."""
        return self.placement.translation

    def to_json(self) -> dict[str, Any]:
        """JSON for the API: the pose for `screen_pose`, the placement in words, its outline
        and the predicted worst ray sigma now and after."""
        p = self.placement
        return {
            **p.to_json(self.image_size),
            "distance_mm": p.distance_mm, "tilt_deg": self.tilt_deg,
            "tilt_azimuth_deg": self.tilt_azimuth_deg,
            "screen_center_px": list(p.centre_px), "image_fraction": p.image_fraction,
            "full_screen_visible": p.visible_fraction >= 1.0,
            "predicted_worst_ray_sigma_urad": {"now": self.worst_before_rad * 1e6,
                                               "after": self.worst_after_rad * 1e6},
            "helps": self.helps, "advice": self.advice,
            "candidates_scored": self.candidates,
            "candidates_rejected_as_repeats": self.rejected_repeats,
            "region_fraction": self.region_fraction, "model_note": self.note,
        }


def fit_session(points: list[PointSet], image_size: tuple[int, int], screen: ScreenGeometry,
                model_name: str = "opencv-rational") -> SessionFit:
    """Fit `model_name` to the session's points (>= 3 poses) as its calibration would; a
    rational fit near 0/0 is refitted there too (`fit_parametric_dense`), and its note is
    this fit's `note`."""
    if model_name not in PARAMETRIC:
        raise ValueError(f"model: guidance predicts with a parametric model "
                         f"({', '.join(PARAMETRIC)}), got {model_name!r}")
    model, poses, _, stats, _ = fit_parametric_dense(points, image_size, model_name, screen)
    return SessionFit(model, [(p.rotation, p.translation) for p in poses],
                      [subsample(p, RAY_SIGMA_POINTS_PER_POSE) for p in points],
                      stats.get("param_std"), stats.get("fit_note", ""))


def suggest_next_pose(fit: SessionFit, screen: ScreenGeometry,
                      min_visible: float = DEFAULT_MIN_VISIBLE) -> Suggestion:
    """The candidate placement that most lowers the worst predicted ray sigma, among those
    that show at least `min_visible` of the screen (1: all of it; less, as by default, lets
    a screen reach past the image's edge and put data in its corners) and do not repeat a
    pose already taken. `fit` may be a calibration's own (its model, fitted poses, training
    points and `param_std`)."""
    if not MIN_VISIBLE <= min_visible <= 1.0:
        raise ValueError(f"min_screen_visible: expected {MIN_VISIBLE}..1, got {min_visible}")
    model = fit.model
    w, h = model.image_size
    free = free_parameters(model, fit.param_std)
    grid = sensor_grid((w, h), *RAY_SIGMA_GRID)
    region = reachable(model, grid)
    jd = direction_jacobian(model, grid, free)
    points = [subsample(p, RAY_SIGMA_POINTS_PER_POSE) for p in fit.points]
    info0 = sum(pose_information(model, r, t, p, free)
                for (r, t), p in zip(fit.poses, points, strict=True))
    before = ray_sigma(jd, covariance(info0))
    worst_before = worst_ray_sigma(model, grid, before)
    sigma = np.nanmedian(np.concatenate([p.sigma_px for p in points]), axis=0)
    samples = sensor_grid((w, h), *_SAMPLE_GRID)
    rays = model.unproject(samples)
    taken = [found.outline_px for r, t in fit.poses
             if (found := place(model, screen, r, t, 0.0)) is not None]
    dist0 = float(np.median([np.linalg.norm(r @ screen_centre_mm(screen) + t)
                             for r, t in fit.poses]))
    cands = candidate_placements(model, screen, dist0, min_visible=min_visible)
    if not cands:
        raise ValueError(f"guidance: no candidate pose shows {100 * min_visible:.0f} % of the "
                         "screen; the screen may be too large for this camera's view at the "
                         "session's distances")
    best: tuple[float, Placement, float, float, np.ndarray] | None = None
    repeats = 0
    for placement, tilt, az in cands:
        if any(_near(placement.outline_px, o, (w, h)) for o in taken):
            repeats += 1
            continue
        pts = planned_points(rays, samples, screen, placement.rotation, placement.translation,
                             sigma)
        if len(pts) < 20:
            continue
        valid = len(pts) / len(samples) * w * h  # pixels the pose would decode
        weight = min(RAY_SIGMA_POINTS_PER_POSE, valid) / len(pts)
        after = ray_sigma(jd, covariance(info0 + weight * pose_information(
            model, placement.rotation, placement.translation, pts, free)))
        score = worst_ray_sigma(model, grid, after)
        if best is None or score < best[0]:
            best = (score, placement, tilt, az, after)
    if best is None:
        raise ValueError(f"guidance: all {len(cands)} candidate poses repeat poses already "
                         "taken; calibrate now, or move the screen closer or farther by hand")
    score, placement, tilt, az, after = best
    helps = bool(score < (1 - MIN_GAIN) * worst_before)
    advice = (f"capture this pose next: the worst predicted ray sigma would fall from "
              f"{worst_before * 1e6:.3g} to {score * 1e6:.3g} urad" if helps else
              f"no pose tried lowers the worst predicted ray sigma ({worst_before * 1e6:.3g} "
              f"urad) by {100 * MIN_GAIN:.0f} % or more: more poses add little; calibrate now "
              "(or lower the decoding noise: longer exposure, more phase steps)")
    shape = (RAY_SIGMA_GRID[1], RAY_SIGMA_GRID[0])
    reach = np.where(region, 1.0, np.nan)
    return Suggestion(placement, tilt, az, worst_before, score, len(cands) - repeats, repeats,
                      helps, advice, (before * reach).reshape(shape),
                      (after * reach).reshape(shape), (w, h), float(region.mean()),
                      "; ".join(n for n in (fit.note, undetermined(fit)) if n))


def undetermined(fit: SessionFit) -> str:
    """Words on distortion coefficients the poses do not pin down (1-sigma above both 1 and
    their value): the predicted sigma then rests on where the fit landed in a flat valley
    and can rise from one pose count to the next ('' when all are determined)."""
    std = fit.param_std or {}
    values = dict(zip(fit.model.param_names(), fit.model.get_params().tolist(), strict=True))
    loose = [k for k, v in values.items() if k not in ("fx", "fy", "cx", "cy")
             and std.get(k, 0.0) > max(1.0, abs(v))]
    if not loose:
        return ""
    worst = max(std[k] for k in loose)
    return (f"{', '.join(loose)} are not individually determined by these poses (1-sigma up "
            f"to {worst:.3g}): their effects nearly cancel, so the predicted ray sigma depends "
            "on where the fit lands and can rise from one pose count to the next; a model "
            "with fewer distortion terms (opencv5 for a mild lens) predicts steadily")


def _near(a: np.ndarray, b: np.ndarray, image_size: tuple[int, int]) -> bool:
    return outline_distance(a, b, image_size) < NEAR_POSE_FRACTION


def session_points(maps: list[DecodedMaps], screen: ScreenGeometry) -> list[PointSet]:
    """Each pose's correspondences, all of them, as the calibration's weighted fit takes them."""
    return [point_set(m, screen) for m in maps]


def plan_next_pose(points: list[PointSet], image_size: tuple[int, int], screen: ScreenGeometry,
                   model_name: str = "opencv-rational",
                   min_visible: float = DEFAULT_MIN_VISIBLE) -> tuple[Suggestion, CameraModel]:
    """Fit `model_name` to the session's points (>= 3 poses) as its calibration would and
    suggest the next pose (`suggest_next_pose`). Returns the suggestion and the fitted model
    it was planned with."""
    fit = fit_session(points, image_size, screen, model_name)
    return suggest_next_pose(fit, screen, min_visible), fit.model
