"""Flange-space planning for the closed loop (a robot places the camera or the screen,
phasecal plans, captures, refits and stops when good enough).

Before the hand-eye is known the loop cannot say which flange pose shows the screen where,
so it starts with `probe_moves`: the flange pose the operator left the robot in (which
shows the screen) and a step back along the tool axis, whose change of scale tells how far
the screen is (`screen_distance_mm`); then `starting_moves`, large turns about a point at
that distance about different axes of the flange, as
hand-eye needs rotations about non-parallel axes and the fit needs tilted views. Once
`MIN_HANDEYE_VIEWS` poses exist, `plan_step` fits the session as its calibration would
(the guidance fit), fits the hand-eye on the same maps, and ranks every candidate screen
placement of the guidance planner by its predicted worst ray sigma, each converted to the
flange pose that shows it through the hand-eye estimate (`flange_for_view`). The caller
keeps the first one its robot can reach: the planner's candidates constrained to the
reachable set.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from calibration.fit.correspondences import subsample
from calibration.guidance import (
    MIN_GAIN,
    NEAR_POSE_FRACTION,
    SessionFit,
    fit_session,
    session_points,
)
from calibration.guidance_placement import (
    DEFAULT_MIN_VISIBLE,
    Placement,
    candidate_placements,
    outline_distance,
    place,
    planned_points,
    screen_centre_mm,
)
from calibration.handeye.pipeline import handeye_from_maps
from calibration.handeye.rigid import Rigid
from calibration.handeye.robot_poses import robot_poses_from_dict
from calibration.handeye.solve import MIN_HANDEYE_VIEWS
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import Plan, ScreenGeometry
from calibration.uncertainty import (
    RAY_SIGMA_GRID,
    RAY_SIGMA_POINTS_PER_POSE,
    covariance,
    direction_jacobian,
    free_parameters,
    pose_information,
    ray_sigma,
    sensor_grid,
    worst_ray_sigma,
)

Mount = Literal["eye-in-hand", "eye-to-hand"]
START_TURN_DEG = 30.0  # the screen's tilt changes a lot, as a well-spread pose list's does
# the starting turns: axis in the flange's x-y plane (deg from x), sign, and the distance to
# the screen as a fraction of the first pose's (closer, farther); the axes pairwise
# non-parallel, as hand-eye needs rotations about different axes
START_TURNS = ((0.0, 1.0, 1.0), (90.0, -1.0, 0.85), (135.0, 1.0, 1.15), (45.0, -1.0, 1.0),
               (22.5, 1.0, 0.85), (112.5, -1.0, 1.15))
MIN_SCREEN_COVERAGE = 0.05  # a capture whose valid pixels cover less has lost the screen
START_STEP_MM = -40.0  # the second starting pose: back along the flange's z axis, no turn
_DISTANCE_POINTS = 2000  # decoded pixels a first pose's distance estimate uses
_SAMPLE_GRID = (32, 24)  # image samples per candidate, as the guidance planner's


@dataclass(frozen=True)
class StartMove:
    """A starting flange pose and why it was chosen."""

    flange: Rigid
    reason: str


@dataclass(frozen=True)
class FlangeCandidate:
    """A planned screen placement, the flange pose that shows it and its predicted effect."""

    flange: Rigid
    screen_pose: dict[str, list[float]]  # rvec, tvec_mm (screen in the camera frame)
    worst_after_rad: float
    words: str

    def to_json(self) -> dict[str, Any]:
        return {"flange": self.flange.to_json(), "screen_pose": self.screen_pose,
                "predicted_worst_ray_sigma_urad": self.worst_after_rad * 1e6,
                "placement": self.words}


@dataclass
class PlanStep:
    """What the loop knows after refitting: the worst ray sigma now, the hand-eye
    (phasecal.handeye/1, None below `MIN_HANDEYE_VIEWS` poses) and the ranked next poses."""

    worst_rad: float
    handeye: dict[str, Any] | None
    candidates: list[FlangeCandidate]
    note: str

    def handeye_sigma(self) -> dict[str, float] | None:
        """The hand-eye's 1-sigma (rotation_mrad, translation_mm), when known."""
        return None if self.handeye is None else dict(self.handeye["stats"]["hand_eye_sigma"])


def probe_moves(rotation: np.ndarray, translation_mm: np.ndarray,
                step_mm: float = START_STEP_MM) -> list[StartMove]:
    """The first two starting poses: the flange pose the robot stands in (`rotation`,
    `translation_mm` in its base frame) and that pose moved `step_mm` along the flange's z
    axis without turning, from which `screen_distance_mm` tells how far the screen is."""
    current = Rigid(np.asarray(rotation, np.float64), np.asarray(translation_mm, np.float64))
    return [StartMove(current, "the flange pose the robot stood in"),
            StartMove(current @ Rigid(np.eye(3), np.array([0.0, 0.0, step_mm])),
                      f"starting set: {step_mm:+g} mm along the flange's z axis, no turn "
                      "(how far the screen is)")]


def starting_moves(rotation: np.ndarray, translation_mm: np.ndarray, count: int,
                   pivot_mm: float, distance_mm: float,
                   turn_deg: float = START_TURN_DEG) -> list[StartMove]:
    """`count` turns of the flange from the pose it stood in (`rotation`, `translation_mm`
    in the robot's base frame) by `turn_deg` about the point `pivot_mm` along the flange's
    z axis (`START_TURNS`), so a screen seen there stays in view while its tilt changes a
    lot, each moved along that axis to a varied fraction of `distance_mm` (the screen's
    signed distance along it, `screen_distance_mm`). Eye-in-hand, the pivot is the screen
    (a camera looking along the tool axis); eye-to-hand, the flange origin (a screen on the
    flange turns about itself)."""
    if not 1 <= count <= len(START_TURNS):
        raise ValueError(f"count: expected 1..{len(START_TURNS)} starting turns, got {count}")
    current = Rigid(np.asarray(rotation, np.float64), np.asarray(translation_mm, np.float64))
    pivot = np.array([0.0, 0.0, pivot_mm])
    moves = []
    for angle, sign, fraction in START_TURNS[:count]:
        unit = np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle)), 0.0])
        turn = Rotation.from_rotvec(sign * np.radians(turn_deg) * unit).as_matrix()
        closer = np.array([0.0, 0.0, (1.0 - fraction) * distance_mm])
        local = Rigid(turn, pivot - turn @ pivot + turn @ closer)  # closer along the new z
        moves.append(StartMove(current @ local, f"starting set: turn {sign * turn_deg:+g} deg "
                               f"about flange axis {np.round(unit, 3).tolist()} through "
                               f"{pivot_mm:.0f} mm along z, {fraction:.0%} of the distance"))
    return moves


def covers_screen(maps: DecodedMaps) -> bool:
    """Whether a capture still shows the screen: valid pixels over `MIN_SCREEN_COVERAGE` of
    the image."""
    h, w = maps.shape
    return bool(maps.mask.sum() >= MIN_SCREEN_COVERAGE * w * h)


def mm_per_px_at_centre(maps: DecodedMaps, screen: ScreenGeometry) -> float:
    """Screen millimetres per image pixel at the image centre (the screen plane's homography
    from the decoded pixels): proportional to the screen's distance along the central ray."""
    h, w = maps.shape
    vs, us = np.nonzero(maps.mask)
    pick = np.linspace(0, len(us) - 1, min(len(us), _DISTANCE_POINTS)).astype(int)
    vs, us = vs[pick], us[pick]
    img = np.stack([us, vs], axis=1).astype(np.float64)
    obj = np.stack([maps.x[vs, us] * screen.pitch_mm[0], maps.y[vs, us] * screen.pitch_mm[1]],
                   axis=1)
    homography, _ = cv2.findHomography(img, obj, cv2.LMEDS)
    if homography is None:
        raise ValueError("the decoded pixels do not fit a screen plane")
    cu, cv = (w - 1) / 2, (h - 1) / 2
    near = np.array([[[cu, cv]], [[cu + 1.0, cv]], [[cu, cv + 1.0]]])
    at = cv2.perspectiveTransform(near, homography).reshape(3, 2)
    jacobian = np.stack([at[1] - at[0], at[2] - at[0]], axis=1)
    return float(np.sqrt(abs(np.linalg.det(jacobian))))


def screen_distance_mm(before: DecodedMaps, after: DecodedMaps, screen: ScreenGeometry,
                       step_mm: float) -> float:
    """The screen's distance along the flange's z axis in `before`, from the change of scale
    after the flange moved `step_mm` along its z axis without turning (`after`): positive
    when moving along +z brings the screen closer. Assumes the camera looks along that
    axis; needs neither the focal length nor the distortion."""
    m0, m1 = mm_per_px_at_centre(before, screen), mm_per_px_at_centre(after, screen)
    if abs(m0 - m1) < 1e-6 * m0:
        raise ValueError("the step along the flange's z axis did not change the screen's "
                         "scale: the camera does not look along it")
    return step_mm * m0 / (m0 - m1)


def flange_for_view(mount: Mount, hand_eye: Rigid, world_target: Rigid,
                    view: Rigid) -> Rigid:
    """The flange pose that shows the screen at `view` (screen -> camera), given the hand-eye
    in phasecal.handeye/1's meaning (eye-in-hand: camera in flange, screen in base;
    eye-to-hand: camera in base, screen in flange)."""
    if mount == "eye-in-hand":  # view = (F X)^-1 Y  ->  F = Y view^-1 X^-1
        return world_target @ view.inverse() @ hand_eye.inverse()
    return hand_eye @ view @ world_target.inverse()  # view = X^-1 F Y  ->  F = X view Y^-1


def _rigid(doc: dict[str, Any]) -> Rigid:
    return Rigid(np.asarray(doc["R"], np.float64), np.asarray(doc["t_mm"], np.float64))


def ranked_placements(fit: SessionFit, screen: ScreenGeometry,
                      min_visible: float = DEFAULT_MIN_VISIBLE
                      ) -> tuple[float, list[tuple[float, Placement]]]:
    """The worst predicted ray sigma now and every candidate placement that does not repeat
    a pose taken, with its predicted worst sigma, best first; the prediction is the guidance
    planner's (`calibration.guidance.suggest_next_pose` keeps only the first of these)."""
    model = fit.model
    w, h = model.image_size
    free = free_parameters(model, fit.param_std)
    grid = sensor_grid((w, h), *RAY_SIGMA_GRID)
    jd = direction_jacobian(model, grid, free)
    points = [subsample(p, RAY_SIGMA_POINTS_PER_POSE) for p in fit.points]
    info0 = sum(pose_information(model, r, t, p, free)
                for (r, t), p in zip(fit.poses, points, strict=True))
    worst_before = worst_ray_sigma(model, grid, ray_sigma(jd, covariance(info0)))
    sigma = np.nanmedian(np.concatenate([p.sigma_px for p in points]), axis=0)
    samples = sensor_grid((w, h), *_SAMPLE_GRID)
    rays = model.unproject(samples)
    taken = [found.outline_px for r, t in fit.poses
             if (found := place(model, screen, r, t, 0.0)) is not None]
    dist0 = float(np.median([np.linalg.norm(r @ screen_centre_mm(screen) + t)
                             for r, t in fit.poses]))
    ranked = []
    for placement, _, _ in candidate_placements(model, screen, dist0, min_visible=min_visible):
        if any(outline_distance(placement.outline_px, o, (w, h)) < NEAR_POSE_FRACTION
               for o in taken):
            continue
        pts = planned_points(rays, samples, screen, placement.rotation, placement.translation,
                             sigma)
        if len(pts) < 20:
            continue
        weight = min(RAY_SIGMA_POINTS_PER_POSE, len(pts) / len(samples) * w * h) / len(pts)
        after = ray_sigma(jd, covariance(info0 + weight * pose_information(
            model, placement.rotation, placement.translation, pts, free)))
        ranked.append((worst_ray_sigma(model, grid, after), placement))
    ranked.sort(key=lambda item: item[0])
    return worst_before, ranked


def plan_step(maps: dict[str, DecodedMaps], plan: Plan, robot_poses: dict[str, Any],
              mount: Mount, model: str, min_visible: float = DEFAULT_MIN_VISIBLE) -> PlanStep:
    """Refit the session (`maps` keyed by pose id, `robot_poses` phasecal.robot-poses/1 with
    the same keys), fit the hand-eye once there are `MIN_HANDEYE_VIEWS` poses, and rank the
    next flange poses that would lower the worst ray sigma by `MIN_GAIN` or more."""
    screen = plan.screen
    h, w = next(iter(maps.values())).shape
    fit = fit_session(session_points(list(maps.values()), screen), (w, h), screen, model)
    worst, ranked = ranked_placements(fit, screen, min_visible)
    if len(maps) < MIN_HANDEYE_VIEWS:
        return PlanStep(worst, None, [], fit.note)
    doc = handeye_from_maps(mount, robot_poses_from_dict(robot_poses), plan, maps, model)
    hand_eye, world_target = _rigid(doc["hand_eye"]), _rigid(doc["world_target"])
    candidates = [
        FlangeCandidate(flange_for_view(mount, hand_eye, world_target,
                                        Rigid(p.rotation, p.translation)),
                        p.screen_pose(), score, p.words((w, h)))
        for score, p in ranked if score < (1 - MIN_GAIN) * worst]
    return PlanStep(worst, doc, candidates, fit.note)
