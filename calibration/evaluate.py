"""Model-agnostic residual statistics: per pose, against the noise floor, held-out poses, maps.

Residuals are camera-pixel differences `project(R S + t) - pixel`. The decoded sigma is
in screen px; the expected camera-px residual of a point is its screen covariance pushed
through the local screen->camera Jacobian of the fitted model and pose, so
`noise_floor_ratio = rms_px / expected_rms_px` is ~1 for an adequate model and >> 1 for a
wrong one (systematic residuals). Residuals are also mapped back to the screen plane, where
the same ratio (`noise_floor_ratio_screen`) weighs every point by its decoded sigma alone:
camera-px sums are dominated by points where the fitted model's screen->camera Jacobian is
huge (near a pole or fold of a distortion that does not fit), which can hide a misfit.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.fit.correspondences import PointSet
from calibration.fit.result import CalibrationResult, PoseEstimate
from calibration.models.base import CameraModel
from calibration.threads import map_in_threads

# A fit whose RMS exceeds the expected noise-floor RMS by more than this is flagged.
ADEQUATE_RATIO = 1.5
# Points beyond this many robust sigmas (and expected sigmas) count as decoding outliers.
OUTLIER_SIGMAS = 5.0
_CHUNK = 1 << 15  # points per chunk of the per-point terms (temporaries stay in cache)


def project_pose(model: CameraModel, rotation: np.ndarray, translation: np.ndarray,
                 screen_mm: np.ndarray) -> np.ndarray:
    """Pixels of screen points (N, 3 mm) under the pose X_cam = R S + t."""
    return model.project(screen_mm @ np.asarray(rotation).T + np.asarray(translation).ravel())


def screen_jacobian(model: CameraModel, rotation: np.ndarray, translation: np.ndarray,
                    points: PointSet) -> np.ndarray:
    """(N, 2, 2) d(camera px)/d(screen px) by central differences of the model's projection."""
    s = points.screen_mm
    jac = np.empty((len(points), 2, 2))
    for axis in range(2):
        step = np.zeros(3)
        step[axis] = 0.5 * points.pitch_mm[axis]
        plus = project_pose(model, rotation, translation, s + step)
        minus = project_pose(model, rotation, translation, s - step)
        jac[:, :, axis] = plus - minus
    return jac


def _point_terms(model: CameraModel, pose: PoseEstimate, points: PointSet
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point: camera-px residual (N, 2), its expected squared size from the decoded
    sigma, and the residual mapped back to the screen (N, 2, screen px)."""
    pred = project_pose(model, pose.rotation, pose.translation, points.screen_mm)
    res = pred - points.pixels
    jac = screen_jacobian(model, pose.rotation, pose.translation, points)
    cov = np.einsum("nij,nj,nkj->nik", jac, points.sigma_px**2, jac)
    with np.errstate(invalid="ignore"):
        res_screen = np.linalg.solve(jac, res[:, :, None])[:, :, 0]
    return res, np.trace(cov, axis1=1, axis2=2), res_screen


def _chunked_terms(model: CameraModel, pose: PoseEstimate, points: PointSet
                   ) -> tuple[np.ndarray, ...]:
    """`_point_terms` in cache-sized chunks over threads (NumPy releases the GIL in its
    loops); the first chunk alone first, so a model's lazily built lookup is built once."""
    n = len(points)
    parts = [slice(a, min(a + _CHUNK, n)) for a in range(0, n, _CHUNK)]
    if len(parts) <= 1:
        return _point_terms(model, pose, points)
    done = [_point_terms(model, pose, points.subset(parts[0]))]
    done += map_in_threads(lambda sl: _point_terms(model, pose, points.subset(sl)), parts[1:])
    return tuple(np.concatenate(arrays) for arrays in zip(*done, strict=True))


def pose_residuals(model: CameraModel, pose: PoseEstimate, points: PointSet) -> dict[str, Any]:
    """Residuals of one pose and their statistics (RMS in camera px and screen px, noise floor)."""
    res, expected2, res_screen = _chunked_terms(model, pose, points)
    mag = np.linalg.norm(res, axis=1)
    finite = np.isfinite(mag) & np.isfinite(expected2)
    robust = 1.4826 * float(np.median(mag[finite])) if finite.any() else np.nan
    limit = OUTLIER_SIGMAS * np.maximum(np.sqrt(expected2), robust)
    inl = finite & (mag <= limit)
    n = int(inl.sum())
    rms = float(np.sqrt(np.mean(mag[inl] ** 2))) if n else float("nan")
    exp_rms = float(np.sqrt(np.mean(expected2[inl]))) if n else float("nan")
    rms_scr = float(np.sqrt(np.mean(np.sum(res_screen[inl] ** 2, axis=1)))) if n else float("nan")
    exp_scr = float(np.sqrt(np.mean(np.sum(points.sigma_px[inl] ** 2, axis=1)))) if n else np.nan
    return {
        "residuals": res, "inliers": inl, "rms_px": rms, "expected_rms_px": exp_rms,
        "rms_screen_px": rms_scr, "expected_rms_screen_px": float(exp_scr),
        "noise_floor_ratio": rms / exp_rms if n and exp_rms > 0 else float("nan"),
        "n_points": n, "outlier_fraction": 1.0 - n / max(len(points), 1),
    }


def summarize(per_pose: list[dict[str, Any]]) -> dict[str, Any]:
    """Overall RMS (camera and screen px), noise-floor ratios and the model-adequacy flag:
    adequate when neither ratio exceeds ADEQUATE_RATIO (a NaN screen ratio: no screen
    residuals, the camera ratio decides)."""
    n = np.array([p["n_points"] for p in per_pose], dtype=np.float64)
    tot = max(float(n.sum()), 1.0)

    def pooled(key: str) -> float:
        return float(np.sqrt(np.nansum(n * np.array([p[key] for p in per_pose]) ** 2) / tot))

    rms, exp = pooled("rms_px"), pooled("expected_rms_px")
    rms_screen, exp_screen = pooled("rms_screen_px"), pooled("expected_rms_screen_px")
    ratio = rms / exp if exp > 0 else float("nan")
    screen = rms_screen / exp_screen if exp_screen > 0 else float("nan")
    return {
        "rms_px": rms, "expected_rms_px": exp, "rms_screen_px": rms_screen,
        "expected_rms_screen_px": exp_screen, "noise_floor_ratio": ratio,
        "noise_floor_ratio_screen": screen,
        "model_adequate": bool(ratio <= ADEQUATE_RATIO and not screen > ADEQUATE_RATIO),
    }


def per_pose_stats(stats: dict[str, Any], index: int) -> dict[str, Any]:
    """The JSON-able part of `pose_residuals` output for `CalibrationResult.stats`."""
    keys = ("rms_px", "expected_rms_px", "rms_screen_px", "expected_rms_screen_px",
            "noise_floor_ratio", "n_points", "outlier_fraction")
    return {"pose": index, **{k: stats[k] for k in keys}}


def attach_residuals(result: CalibrationResult, points: list[PointSet],
                     indices: list[int]) -> list[dict[str, Any]]:
    """Evaluate each fitted pose, store residuals in the result and return per-pose stats."""
    out = []
    for pose, pts, idx in zip(result.poses, points, indices, strict=True):
        st = pose_residuals(result.model, pose, pts)
        pose.rms_px, pose.rms_screen_px, pose.n_points = (
            st["rms_px"], st["rms_screen_px"], st["n_points"])
        result.residuals[idx] = st["residuals"]
        result.residual_pixels[idx] = pts.pixels
        out.append(per_pose_stats(st, idx))
    return out


def heldout_errors(model: CameraModel, points: list[PointSet], indices: list[int],
                   rng: np.random.Generator) -> dict[str, Any]:
    """Error on poses not used in the fit: pose by robust PnP with the fitted model, then RMS."""
    from calibration.fit.classic.pnp import estimate_pose

    per = []
    for pts, idx in zip(points, indices, strict=True):
        r, t, _ = estimate_pose(model, pts, rng)
        st = pose_residuals(model, PoseEstimate(r, t), pts)
        per.append(per_pose_stats(st, idx))
    return {"per_pose": per, **summarize(per)} if per else {}
