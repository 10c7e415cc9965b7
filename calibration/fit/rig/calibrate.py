"""Calibrate a rig: check the inputs and the view graph, start each camera from its own fit,
fit every camera's model, its extrinsics and each view's target pose jointly, drop gross
outliers, and report the extrinsics with their covariance and held-out views' scores."""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from calibration.fit.correspondences import point_set, subsample
from calibration.fit.registry import model_spec
from calibration.fit.rig.blocks import (
    Block,
    maps_pixel_block,
    maps_ray_block,
    observation_block,
)
from calibration.fit.rig.graph import check_connected, views_by_camera
from calibration.fit.rig.heldout import score_view
from calibration.fit.rig.inputs import RigInput
from calibration.fit.rig.options import RigOptions
from calibration.fit.rig.problem import RigCameraState, RigProblem
from calibration.fit.rig.result import RigResult
from calibration.fit.rig.start import CameraStart, chain_extrinsics, start_camera, view_poses
from calibration.fit.rig.transforms import Transform, compose
from calibration.models.base import CameraModel
from calibration.models.sgcc import SGCCBase
from calibration.shared.plan import ScreenGeometry
from calibration.shared.progress import CancelCheck, ProgressFn, check_cancelled
from calibration.shared.rig_model import RigCamera, RigModel


def _check_inputs(inputs: list[RigInput], models: Mapping[str, str],
                  heldout_views: list[str]) -> list[str]:
    """Cameras in input order; ValueError on duplicates, unknown models, mixed image sizes."""
    cameras = list(dict.fromkeys(i.camera for i in inputs))
    if len(cameras) < 2:
        raise ValueError(f"cameras: a rig needs >= 2 cameras, got {cameras} (calibrate one "
                         "camera without CAMERA/VIEW= prefixes)")
    seen: set[tuple[str, str]] = set()
    for i in inputs:
        if (i.camera, i.view) in seen:
            raise ValueError(f"{i.camera}/{i.view}: given twice")
        seen.add((i.camera, i.view))
    for cam in cameras:
        if cam not in models:
            raise ValueError(f"model: no model named for camera {cam!r}")
        model_spec(models[cam])
        sizes = sorted({i.image_size for i in inputs if i.camera == cam})
        if len(sizes) > 1:
            raise ValueError(f"camera {cam}: image sizes differ between views {sizes}")
    unknown = sorted(set(heldout_views) - {i.view for i in inputs})
    if unknown:
        raise ValueError(f"heldout: unknown view(s) {unknown}")
    return cameras


def _block(inp: RigInput, start: CameraStart, to_camera: Transform,
           screen: ScreenGeometry | None, max_points: int) -> Block:
    """The residual block of one input at the start values: decoded maps of a held sGCC
    camera as spline terms (their exact derivatives carry its spline's uncertainty into
    the covariance), of any other held model as rays."""
    if inp.observations is not None:
        obs = inp.observations
        used = obs.used()
        return observation_block(inp.camera, inp.view, start.model, obs.image_xy[used],
                                 obs.target_xyz[used], obs.weights()[used], obs.sigma_px)
    assert inp.maps is not None and screen is not None
    pts = subsample(point_set(inp.maps, screen), max_points)
    if start.free.any() or isinstance(start.model, SGCCBase):
        return maps_pixel_block(inp.camera, inp.view, start.model, to_camera, pts,
                                held=not start.free.any())
    return maps_ray_block(inp.camera, inp.view, start.model, pts)


def heldout_block(inp: RigInput, model: CameraModel, screen: ScreenGeometry | None,
                   max_points: int, estimated_sigma: float | None) -> Block:
    """A held-out input's block through the fitted model: decoded maps as rays (their miss on
    the screen in mm needs no pose to weight it), observations in pixels (as in the fit)."""
    if inp.maps is not None:
        assert screen is not None
        return maps_ray_block(inp.camera, inp.view, model,
                              subsample(point_set(inp.maps, screen), max_points))
    obs = inp.observations
    assert obs is not None
    used = obs.used()
    sigma = obs.sigma_px if obs.sigma_px is not None else estimated_sigma
    return observation_block(inp.camera, inp.view, model, obs.image_xy[used],
                             obs.target_xyz[used], obs.weights()[used], sigma)


def _robust_keep(blocks: list[Block], residuals: list[np.ndarray], k: float) -> list[Block]:
    """Blocks without the points beyond k robust sigmas (whitened residual components)."""
    flat = np.concatenate([np.abs(r).ravel() for r in residuals])
    flat = flat[np.isfinite(flat)]
    scale = 1.4826 * float(np.median(flat)) if flat.size else 1.0
    out = []
    for b, r in zip(blocks, residuals, strict=True):
        keep = np.all(np.isfinite(r), axis=1) & (np.max(np.abs(r), axis=1) <= k * scale)
        out.append(b.subset(keep))
    return out


def _rescale_unknown_sigma(blocks: list[Block], residuals: list[np.ndarray]) -> dict[str, float]:
    """Observations without a stated sigma: per camera, the pixel sigma estimated from their
    residuals (scales their weights in place); returns camera -> sigma px."""
    found: dict[str, float] = {}
    for cam in sorted({b.camera for b in blocks if not b.sigma_known}):
        rs = [r for b, r in zip(blocks, residuals, strict=True)
              if b.camera == cam and not b.sigma_known]
        r = np.concatenate([x.ravel() for x in rs])
        sigma = float(np.sqrt(np.nanmean(r**2)))
        if sigma > 0:
            for b in blocks:
                if b.camera == cam and not b.sigma_known:
                    b.whiten = b.whiten / sigma
            found[cam] = sigma
    return found


def _block_stats(blocks: list[Block], problem: RigProblem, x: np.ndarray) -> list[dict[str, Any]]:
    """Per camera and view: RMS residual (px, or mm on the target for held rays), whitened
    RMS and point count."""
    problem.set_models(x)
    rows = []
    for b in blocks:
        tf = compose(problem.extrinsic(x, b.camera), problem.pose(x, b.view))
        model = problem.cameras[b.camera].model
        w, raw = b.residuals(model, tf), b.raw_residuals(model, tf)
        ok = np.all(np.isfinite(w), axis=1)
        rows.append({"camera": b.camera, "view": b.view,
                     ("rms_mm" if b.kind == "ray" else "rms_px"):
                         float(np.sqrt(np.mean(np.sum(raw[ok] ** 2, axis=1)))),
                     "whitened_rms": float(np.sqrt(np.mean(w[ok] ** 2))),
                     "n_points": int(ok.sum())})
    return rows


def calibrate_rig(
    inputs: list[RigInput], models: str | Mapping[str, str],
    screen: ScreenGeometry | None = None, *, reference: str | None = None,
    options: RigOptions | dict[str, Any] | None = None,
    model_options: Mapping[str, dict[str, Any]] | None = None,
    heldout_views: list[str] | None = None, progress: ProgressFn | None = None,
    cancelled: CancelCheck | None = None,
) -> RigResult:
    """Fit a rig to maps and/or target observations named by camera and view.

    `models`: one model name for every camera, or camera -> name; `model_options`: camera
    -> that model's options (for its own start fit and which parameters are fitted);
    `reference`: the camera whose frame is the rig's (default the first camera given);
    `heldout_views`: views left out of the fit and scored through the extrinsics."""
    t0 = time.perf_counter()
    opts = options if isinstance(options, RigOptions) else RigOptions.model_validate(options or {})
    held = sorted(set(heldout_views or []))
    names = list(dict.fromkeys(i.camera for i in inputs))
    per_camera = {c: models for c in names} if isinstance(models, str) else dict(models)
    cameras = _check_inputs(inputs, per_camera, held)
    reference = cameras[0] if reference is None else reference
    if reference not in cameras:
        raise ValueError(f"reference: expected one of {cameras}, got {reference!r}")
    train = [i for i in inputs if i.view not in held]
    check_connected(views_by_camera((i.camera, i.view) for i in train))

    def step(k: int, n: int, what: str) -> None:
        check_cancelled(cancelled, "rig calibration")
        if progress is not None:
            progress(k, n, what)

    n_steps = len(cameras) + 3
    starts: dict[str, CameraStart] = {}
    for k, cam in enumerate(cameras):
        step(k, n_steps, f"camera {cam}: own fit ({per_camera[cam]})")
        starts[cam] = start_camera(cam, [i for i in train if i.camera == cam], per_camera[cam],
                                   screen, dict((model_options or {}).get(cam, {})))
    ext = chain_extrinsics(starts, reference)
    order = [reference, *[c for c in cameras if c != reference]]
    poses = view_poses(starts, ext, order)
    views = list(dict.fromkeys(i.view for i in train))
    unposed = [v for v in views if v not in poses]
    if unposed:
        raise ValueError(f"views {unposed}: no camera's own fit placed the target in them")
    blocks = [_block(i, starts[i.camera], compose(ext[i.camera], poses[i.view]), screen,
                     opts.max_points_per_view) for i in train]
    states = {c: RigCameraState.of(starts[c].model, starts[c].free) for c in cameras}
    problem = RigProblem(states, reference, views, blocks)
    step(len(cameras), n_steps, "joint fit")
    x, info = problem.solve(problem.pack(ext, poses), max_iterations=opts.max_iterations)
    residuals = problem.block_residuals(x)
    estimated = _rescale_unknown_sigma(blocks, residuals)
    blocks = _robust_keep(blocks, problem.block_residuals(x), opts.outlier_sigmas)
    dropped = problem.n_data // 2 - sum(len(b) for b in blocks)
    problem = RigProblem(states, reference, views, blocks)
    step(len(cameras) + 1, n_steps, "joint fit without outliers")
    x, info = problem.solve(x, max_iterations=opts.max_iterations)
    step(len(cameras) + 2, n_steps, "covariance")
    cov, chi2 = problem.covariance(x)
    for cam in cameras:
        idx = problem.intrinsics[cam]
        states[cam].set_covariance(cov[np.ix_(idx, idx)])
    rig_cams: dict[str, RigCamera] = {}
    extr_stats: dict[str, Any] = {}
    for cam in cameras:
        rot, t = problem.extrinsic(x, cam)
        idx = problem.extrinsics.get(cam)
        c6 = np.zeros((6, 6)) if idx is None else cov[np.ix_(idx, idx)]
        rig_cams[cam] = RigCamera(states[cam].model, rot, t, c6)
        sd = np.sqrt(np.clip(np.diag(c6), 0, None))
        extr_stats[cam] = {"rotation_sigma_mrad": (sd[:3] * 1e3).tolist(),
                           "translation_sigma_mm": sd[3:].tolist(),
                           "baseline_mm": float(np.linalg.norm(-rot.T @ t))}
    per_block = _block_stats(blocks, problem, x)
    stats: dict[str, Any] = {
        "reference": reference,
        "models": {c: per_camera[c] for c in cameras},
        "intrinsics_fixed": [c for c in cameras if not states[c].free.any()],
        "intrinsics_rays_in_covariance": [
            c for c in cameras if states[c].held_spline_covariance() is not None],
        "intrinsics_note": ("a camera listed in intrinsics_fixed keeps its rays from its own "
                            "fit; the extrinsics' covariance includes their uncertainty (its "
                            "own fit's covariance) for the cameras listed in "
                            "intrinsics_rays_in_covariance, and leaves it out for the others"),
        "reduced_chi2": chi2, "iterations": info["iterations"], "converged": info["converged"],
        "training_views": views, "per_view": per_block, "extrinsics": extr_stats,
        "outliers_dropped": int(dropped), "n_points": int(sum(len(b) for b in blocks)),
        "options": opts.model_dump(),
    }
    if estimated:
        stats["estimated_sigma_px"] = estimated
    for cam in cameras:
        rows = [r for r in per_block if r["camera"] == cam]
        fitted = {k: starts[cam].stats[k] for k in ("rms_px", "reduced_chi2")
                  if k in starts[cam].stats}
        states[cam].model.stats = {"rig_reference": reference, "own_fit": fitted,
                                   "per_view": rows}
    if held:
        step(len(cameras) + 2, n_steps, "held-out views")
        models_now = {c: states[c].model for c in cameras}
        extr_now = {c: problem.extrinsic(x, c) for c in cameras}
        scored = []
        for view in held:
            hb = [heldout_block(i, models_now[i.camera], screen, opts.max_points_per_view,
                                 estimated.get(i.camera))
                  for i in inputs if i.view == view]
            scored.append(score_view(view, hb, models_now, extr_now, order))
        stats["heldout"] = scored
    stats["wall_s"] = time.perf_counter() - t0
    rig = RigModel(reference, rig_cams, {k: stats[k] for k in (
        "reduced_chi2", "extrinsics", "intrinsics_fixed", "intrinsics_rays_in_covariance",
        "models", "n_points")})
    return RigResult(rig, {v: problem.pose(x, v) for v in views}, stats)
