"""Start values of the joint fit: each camera's own single-camera fit (its model and the
target pose in each of its views), then each camera's pose relative to the reference camera
chained through the views they share, and each view's target pose in the reference frame."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.fit.classic.options import MIN_POSES as CLASSIC_MIN_POSES
from calibration.fit.classic.options import ParametricOptions
from calibration.fit.classic.parametric import fit_parametric
from calibration.fit.correspondences import PointSet
from calibration.fit.dispatch import calibrate
from calibration.fit.registry import model_spec
from calibration.fit.result import PoseEstimate
from calibration.fit.rig.graph import chain_order, views_by_camera
from calibration.fit.rig.inputs import RigInput
from calibration.fit.rig.transforms import Transform, compose, invert, mean_transform
from calibration.fit.sparse.calibrate import REFUSED, parse_observation_options
from calibration.fit.sparse.sgcc import fit_sgcc_observations
from calibration.models.base import CameraModel
from calibration.shared.plan import ScreenGeometry

# Target points further than this from the z = 0 plane make a target non-flat (mm).
_FLAT_TOLERANCE_MM = 1e-6


@dataclass
class CameraStart:
    """A camera's single-camera fit: its model, which parameters the joint fit moves, and the
    target-to-camera transform of each view it was fitted on."""

    model: CameraModel
    free: np.ndarray
    poses: dict[str, Transform]
    stats: dict[str, Any]


def _free_mask(model: CameraModel, family: str, options: dict[str, Any],
               from_observations: bool) -> np.ndarray:
    """The parameters the joint fit moves: all of a parametric model's (less the thin prism
    unless asked for), all of an sGCC model's fitted to observations (its spline, in its
    gauge), none of a generic model's fitted to maps (its rays stay as its own fit left
    them)."""
    moved = family == "classic" or (family == "sgcc" and from_observations)
    free = np.full(model.get_params().size, moved)
    if model.type_name == "opencv-rational" and not options.get("thin_prism", False):
        free[4 + 8:] = False
    return free


def _observation_points(inp: RigInput) -> PointSet:
    """A flat target's observations as point correspondences (target mm as screen px at a
    1 mm pitch)."""
    obs = inp.observations
    assert obs is not None
    used = obs.used()
    xyz = obs.target_xyz[used]
    if np.any(np.abs(xyz[:, 2]) > _FLAT_TOLERANCE_MM):
        raise ValueError(f"{inp.camera}/{inp.view}: target_xyz: the start fit needs a flat "
                         "target (z = 0 for every point)")
    sigma = 1.0 / obs.weights()[used]
    return PointSet(obs.image_xy[used], xyz[:, :2], np.column_stack([sigma, sigma]), (1.0, 1.0))


def _generic_start(obs: list[RigInput], model_name: str, n_maps: int,
                   options: dict[str, Any]
                   ) -> tuple[CameraModel, list[PoseEstimate], dict[str, Any]]:
    """A generic model's start from observations: the single-camera sparse sGCC fit of the
    camera's own views (its mesh chosen for their points); raygrid is refused."""
    spec = model_spec(model_name)
    if model_name in REFUSED:
        raise ValueError(f"{model_name}: a rig fits it from decoded maps only (this camera "
                         f"has {n_maps} views of maps, it needs >= {spec.min_poses}): "
                         f"{REFUSED[model_name]}")
    fit = fit_sgcc_observations([i.observations for i in obs], model_name,
                                parse_observation_options(model_name, options))
    return fit.model, fit.poses, fit.stats


def start_camera(camera: str, inputs: list[RigInput], model_name: str,
                 screen: ScreenGeometry | None, options: dict[str, Any]) -> CameraStart:
    """Fit one camera on its own views (decoded maps if it has enough, else observations)."""
    spec = model_spec(model_name)
    maps = [i for i in inputs if i.maps is not None]
    obs = [i for i in inputs if i.observations is not None]
    opts = dict(options)
    if spec.family == "classic":
        opts.setdefault("points", "sampled")  # the joint fit is the weighted one
    from_observations = False
    try:
        if len(maps) >= spec.min_poses or not obs:
            if screen is None:
                raise ValueError("plan: decoded maps need the plan's screen geometry")
            res = calibrate([i.maps for i in maps], screen, model_name, options=opts)
            model, poses, stats = res.model, res.poses, res.stats
            views = [i.view for i in maps]
        elif spec.family != "classic":
            from_observations = True
            model, poses, stats = _generic_start(obs, model_name, len(maps), opts)
            views = [i.view for i in obs]
        else:
            from_observations = True
            if len(obs) < CLASSIC_MIN_POSES:
                raise ValueError(f"needs >= {CLASSIC_MIN_POSES} views, got {len(obs)}")
            size = obs[0].image_size
            if any(i.image_size != size for i in obs):
                raise ValueError(f"image sizes differ between views "
                                 f"{sorted({i.image_size for i in obs})}")
            parsed = ParametricOptions.model_validate(opts)
            model, poses, _, stats = fit_parametric(
                [_observation_points(i) for i in obs], size, model_name, parsed)
            views = [i.view for i in obs]
    except ValueError as exc:  # DegenerateError included: say which camera
        raise ValueError(f"camera {camera}: {exc}") from None
    return CameraStart(model, _free_mask(model, spec.family, opts, from_observations),
                       {v: (p.rotation, p.translation) for v, p in zip(views, poses, strict=True)},
                       stats)


def chain_extrinsics(starts: dict[str, CameraStart], reference: str) -> dict[str, Transform]:
    """Each camera's reference-to-camera transform, chained breadth-first from the reference
    over shared views (a robust average over each link's shared views)."""
    views = views_by_camera((c, v) for c, s in starts.items() for v in s.poses)
    ext: dict[str, Transform] = {reference: (np.eye(3), np.zeros(3))}
    for cam, parent, shared in chain_order(views, reference):
        links = [compose(starts[cam].poses[v], invert(starts[parent].poses[v])) for v in shared]
        ext[cam] = compose(mean_transform(links), ext[parent])
    missing = sorted(set(starts) - set(ext))
    if missing:
        raise ValueError(f"cameras: {missing} share no view with a fitted pose with the other "
                         "cameras (each camera's own fit must use a shared view)")
    return ext


def view_poses(starts: dict[str, CameraStart], ext: dict[str, Transform],
               order: list[str]) -> dict[str, Transform]:
    """Each view's target-to-reference transform, from the first camera in `order` that
    has the view."""
    poses: dict[str, Transform] = {}
    for cam in order:
        for view, tf in starts[cam].poses.items():
            poses.setdefault(view, compose(invert(ext[cam]), tf))
    return poses
