"""Fit the `raygrid` model: per-pixel rays and screen poses jointly (Sturm–Ramalingam).

Poses start from OpenCV's rational model (`sgcc/initial.py: initial_state`); with the poses fixed,
each table pixel's ray is fitted in closed form to its 3D screen points over the poses
(weighted total least squares by stacked 3x3 `eigh`; central: through the origin). Then
Gauss-Newton on all rays and poses together: the per-pixel ray blocks (2 or 4 parameters)
are eliminated by a Schur complement, leaving a 6J x 6J pose system solved by a Jacobi-scaled
pseudo-inverse that drops the gauge (rotation; translation too when non-central). A plain
alternation (rays | poses) converges far too slowly along the joint weak directions, hence
the joint step. Residual: the ray, moved into the pose's screen frame, meets z = 0 at Q;
e = (Q - S) / sigma (docs/physics.md section 6). Pixels seen in < 2 poses get NaN rays. Ray
covariance includes pose uncertainty (gauge projected out), scaled by max(1, chi2/dof).
Options: `central` (true), `grid_step` (1 up to 640x480, else 2), `max_iterations` (30),
`tolerance` (1e-9 relative cost change), `cut_sigmas` (8, hard outlier cut in sigmas).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from calibration.evaluate import ADEQUATE_RATIO, summarize
from calibration.fit.heldout import split_heldout
from calibration.fit.observations import PoseObs, observations
from calibration.fit.raygrid.options import RaygridOptions
from calibration.fit.raygrid.solve import (
    Observations,
    cost_and_inliers,
    initial_rays,
    joint_step,
    mask_sparse,
    node_observations,
    pixel_residuals,
    ray_covariance,
    ray_weights,
    refine_poses,
)
from calibration.fit.registry import model_spec
from calibration.fit.result import CalibrationResult, PoseEstimate
from calibration.fit.sgcc.initial import initial_state, pose_from_model
from calibration.models.bspline import SplineGrid
from calibration.models.raygrid import RayGridModel, default_grid_step
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import ScreenGeometry
from calibration.shared.progress import CancelCheck, Cancelled, ProgressFn


def _heldout(
    model: RayGridModel, obs: list[PoseObs], indices: list[int], pitch: np.ndarray, cut: float
) -> dict[str, Any]:
    """Pose-only fit of held-out poses with the rays fixed; residual statistics in the
    parametric models' layout ({per_pose, pooled rms/noise floor}, `evaluate.summarize`).

    The held-out residual also carries the rays' own noise, so its noise-floor ratio sits
    above 1 (about sqrt(1 + 2/J) for J training poses) for a correct model.
    """
    rows = []
    for ob, index in zip(obs, indices, strict=True):
        rc0, tc0 = pose_from_model(model.unproject, ob)
        o, d = model.unproject(ob.pixels)
        one = Observations(ob.pixels, ob.screen_mm[None], ob.sigma_mm[None],
                           np.ones((1, len(d)), dtype=bool))
        rc, tc = rc0[None], tc0[None]
        inl = one.valid & np.all(np.isfinite(d), axis=1)[None]
        for _ in range(3):
            rc, tc = refine_poses(rc, tc, o, d, one, ray_weights(one, inl))
            _, inl, res = cost_and_inliers(rc, tc, o, d, one, cut)
        px, exp2 = pixel_residuals(model, rc[0], tc[0], ob.pixels, res[0], ob.sigma_mm)
        ok = inl[0] & np.all(np.isfinite(px), axis=1)
        n = int(ok.sum())
        rms = float(np.sqrt(np.mean(np.sum(px[ok] ** 2, axis=1))))
        expected = float(np.sqrt(np.mean(exp2[ok])))
        rows.append({
            "pose": index,
            "n_points": n,
            "rms_px": rms,
            "expected_rms_px": expected,
            "noise_floor_ratio": rms / expected,
            "rms_screen_px": float(np.sqrt(np.mean(np.sum((res[0][ok] / pitch) ** 2, axis=1)))),
            "expected_rms_screen_px": float(
                np.sqrt(np.mean(np.sum((ob.sigma_mm[ok] / pitch) ** 2, axis=1)))
            ),
            "chi2_dof": float(np.sum((res[0][ok] / ob.sigma_mm[ok]) ** 2) / max(2 * n - 6, 1)),
            "outlier_fraction": 1.0 - n / max(len(ob.pixels), 1),
        })
    return {"per_pose": rows, **summarize(rows)}


def calibrate_raygrid(
    maps: Sequence[DecodedMaps],
    screen: ScreenGeometry,
    model: str = "raygrid",
    *,
    options: RaygridOptions | dict[str, Any] | None = None,
    heldout: Sequence[int] | None = None,
    progress: ProgressFn | None = None,
    cancelled: CancelCheck | None = None,
) -> CalibrationResult:
    """Fit a raygrid model to the poses not in `heldout`; held-out poses are validated."""
    opts: RaygridOptions = model_spec(model).parse_options(options)
    maps, held_maps, held = split_heldout(maps, heldout, "raygrid")
    t0 = time.perf_counter()
    h, w = maps[0].shape
    step = opts.grid_step or default_grid_step((w, h))
    full = observations(maps, screen)
    for j, fo in enumerate(full):
        if len(fo.pixels) < 100:
            raise ValueError(f"maps[{j}]: only {len(fo.pixels)} valid pixels; need >= 100")
    init = initial_state(full, SplineGrid((w, h), (4, 4)), 2)
    rc, tc = np.stack(init.rc), np.stack(init.tc)
    ob = node_observations(maps, screen, step)
    inl = ob.valid.copy()
    history: list[float] = []
    converged = False
    iterations = 0
    o, d = initial_rays(rc, tc, ob, ray_weights(ob, inl), opts.central, opts.cut_sigmas)
    _, inl, _ = cost_and_inliers(rc, tc, o, d, ob, opts.cut_sigmas)
    wts = ray_weights(ob, inl)
    o, d = mask_sparse(o, d, wts)
    for iterations in range(1, opts.max_iterations + 1):
        if cancelled is not None and cancelled():
            raise Cancelled("raygrid: calibration cancelled")
        rc, tc, o, d = joint_step(rc, tc, o, d, ob, wts, opts.central)
        cost, inl, _ = cost_and_inliers(rc, tc, o, d, ob, opts.cut_sigmas)
        history.append(cost)
        wts = ray_weights(ob, inl)
        if progress is not None:
            progress(iterations, opts.max_iterations, f"raygrid: cost {cost:.6g}")
        if len(history) > 1 and abs(history[-2] - cost) <= opts.tolerance * history[-2]:
            converged = True
            break
    o, d = mask_sparse(o, d, wts)
    cost, inl, res_mm = cost_and_inliers(rc, tc, o, d, ob, opts.cut_sigmas)
    cov_raw, gauge_dims = ray_covariance(rc, tc, o, d, ob, ray_weights(ob, inl), opts.central)
    k = 2 if opts.central else 4
    covered = np.all(np.isfinite(d), axis=1)
    dof = 2 * int(inl.sum()) - k * int(covered.sum()) - 6 * len(rc)
    if dof <= 0:
        raise ValueError(
            f"raygrid: {2 * int(inl.sum())} screen coordinates at grid_step {step} do not "
            f"over-determine {k * int(covered.sum())} ray and {6 * len(rc)} pose parameters; "
            "use a finer grid_step or more poses")
    chi2_dof = cost / max(dof, 1)
    cov = cov_raw * max(1.0, chi2_dof)
    ang = np.sqrt(cov[:, 0, 0] + cov[:, 1, 1])
    org = np.sqrt(cov[:, 2, 2] + cov[:, 3, 3]) if not opts.central else None
    shape = ((h - 1) // step + 1, (w - 1) // step + 1)
    model = RayGridModel(
        (w, h),
        step,
        d.reshape(*shape, 3),
        None if opts.central else o.reshape(*shape, 3),
        ang.reshape(shape),
        None if org is None else org.reshape(shape),
    )
    poses, per_pose, res_px, pix_out = [], [], {}, {}
    expected2: list[np.ndarray] = []
    screen2: list[np.ndarray] = []  # per inlier: squared screen residual, its expected size
    pitch = np.asarray(screen.pitch_mm)
    for j in range(len(rc)):
        px, exp2 = pixel_residuals(model, rc[j], tc[j], ob.pixels, res_mm[j], ob.sigma[j])
        ok = inl[j] & np.all(np.isfinite(px), axis=1)
        expected2.append(exp2[ok])
        screen2.append(np.stack([np.sum((res_mm[j][inl[j]] / pitch) ** 2, axis=1),
                                 np.sum((ob.sigma[j][inl[j]] / pitch) ** 2, axis=1)]))
        rms_px = float(np.sqrt(np.mean(np.sum(px[ok] ** 2, axis=1))))
        rms_scr = float(np.sqrt(np.mean(screen2[-1][0])))
        poses.append(PoseEstimate(rc[j].T, -rc[j].T @ tc[j], rms_px, rms_scr, int(inl[j].sum())))
        per_pose.append({
            "pose": j,
            "rms_px": rms_px,
            "rms_screen_px": rms_scr,
            "n_points": int(inl[j].sum()),
            "n_outliers": int((ob.valid[j] & covered & ~inl[j]).sum()),
        })
        res_px[j], pix_out[j] = px[ok], ob.pixels[ok]
    all_px = np.concatenate([res_px[j] for j in res_px])
    rms_px = float(np.sqrt(np.mean(np.sum(all_px**2, axis=1))))
    # Training residuals of a per-pixel fit are shrunk by its degrees of freedom.
    shrink = dof / max(2 * inl.sum(), 1)
    expected_rms = float(np.sqrt(np.mean(np.concatenate(expected2)) * shrink))
    # the same ratio in the screen plane (evaluate.py: camera px can hide a misfit where
    # the screen->camera Jacobian is large)
    scr2 = np.concatenate(screen2, axis=1)
    rms_screen = float(np.sqrt(np.mean(scr2[0])))
    expected_screen = float(np.sqrt(np.mean(scr2[1]) * shrink))
    ratio, ratio_screen = rms_px / expected_rms, rms_screen / expected_screen
    stats: dict[str, Any] = {
        "model": "raygrid",
        "central": opts.central,
        "grid_step": step,
        "rms_px": rms_px,
        "expected_rms_px": expected_rms,
        "rms_screen_px": rms_screen,
        "expected_rms_screen_px": expected_screen,
        "noise_floor_ratio": ratio,
        "noise_floor_ratio_screen": ratio_screen,
        "model_adequate": bool(ratio <= ADEQUATE_RATIO and not ratio_screen > ADEQUATE_RATIO),
        "per_pose": per_pose,
        "iterations": iterations,
        "converged": converged,
        "cost": cost,
        "cost_history": history,
        "chi2_dof": chi2_dof,
        "gauge_dims": gauge_dims,
        "coverage": float(covered.mean()),
        "ray_std_rad_median": float(np.nanmedian(ang)),
        "ray_std_rad_max": float(np.nanmax(ang)),
        "param_std": {"ray_angle_rad_median": float(np.nanmedian(ang))},
    }
    if org is not None:
        stats["origin_std_mm_median"] = float(np.nanmedian(org))
    if held_maps:
        stats["heldout"] = _heldout(
            model, observations(held_maps, screen), held, pitch, opts.cut_sigmas
        )
    stats["wall_s"] = time.perf_counter() - t0
    model.stats = stats
    return CalibrationResult(model, poses, stats, pix_out, res_px)
