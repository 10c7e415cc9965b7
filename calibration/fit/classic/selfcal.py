"""Self-calibration under general motion from vanishing points (Chang, Wang & Wang).

"Camera Self-calibration Based on the Vanishing Points".

The camera moves and rotates; vanishing points of >= 4 world directions (the edge
directions of two non-parallel rectangles, no three of them coplanar) are tracked across
images. Translation does not move vanishing points, so those of image i map to those of
image j by the infinite homography H_ij = K R_ij K^-1, fitted by DLT on the homogeneous
points; every image pair's H enters the linear H C H^T = C of `classic.rotation`, and K
follows by Cholesky (a clear error when K K^T is not positive definite, as the paper warns).
That is the paper's method. phasecal then refines it by maximum likelihood: vanishing point
of direction d_k in image i = K R_i d_k (R_0 = I), residuals in the tangent space of the
observed unit points, whitened by their covariances; std from the Gauss-Newton covariance.
"""

from __future__ import annotations

import itertools
from typing import Any

import cv2
import numpy as np
import scipy.optimize

from calibration.fit.classic.estimate import PARAMS, IntrinsicsEstimate, monte_carlo_std, normalizer
from calibration.fit.classic.lines import Point, sample_points
from calibration.fit.classic.rotation import rotation_intrinsics
from calibration.fit.ransac import DegenerateError

_MC_SAMPLES = 200


def homogeneous_homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """H with dst ~ H src from >= 4 homogeneous point pairs (N, 3), no three collinear.

    Cross-product DLT (x' x H x = 0), so points at infinity are fine; the points should be
    in normalized coordinates (see `estimate.normalizer`).
    """
    s = src / np.linalg.norm(src, axis=1, keepdims=True)
    d = dst / np.linalg.norm(dst, axis=1, keepdims=True)
    if len(s) < 4:
        raise DegenerateError(f"infinite homography needs >= 4 vanishing points, got {len(s)}")
    rows = []
    for x, y in zip(s, d, strict=True):
        z = np.zeros(3)
        rows += [np.concatenate([z, -y[2] * x, y[1] * x]),
                 np.concatenate([y[2] * x, z, -y[0] * x]),
                 np.concatenate([-y[1] * x, y[0] * x, z])]
    _, sv, vt = np.linalg.svd(np.array(rows))
    if sv[-2] < 1e-8 * sv[0]:
        raise DegenerateError("infinite homography: three of the directions are coplanar "
                              "(e.g. both rectangles share an edge direction)")
    return vt[-1].reshape(3, 3)


def linear_selfcal(vps: np.ndarray, t: np.ndarray) -> np.ndarray:
    """K in pixels from (images, directions, 3) homogeneous pixel vanishing points."""
    vn = vps @ t.T
    hs = [homogeneous_homography(vn[i], vn[j])
          for i, j in itertools.combinations(range(len(vn)), 2)]
    k = np.linalg.inv(t) @ rotation_intrinsics(hs)
    return k / k[2, 2]


def _tangent_whiteners(tracks: list[list[Point]]) -> tuple[np.ndarray, np.ndarray]:
    """Per observation: (3, 2) tangent basis B and (2, 2) whitening W (W^T W = (B^T C B)^-1)."""
    bases, whit = [], []
    for tr in tracks:
        for pt in tr:
            _, _, vt = np.linalg.svd(pt.p[None, :])
            b = vt[1:].T
            c2 = b.T @ pt.cov @ b
            evals, evecs = np.linalg.eigh(c2)
            if evals.min() <= 0:
                raise DegenerateError("self-calibration refinement needs vanishing-point "
                                      "covariances (fit them from lines)")
            bases.append(b)
            whit.append((evecs / np.sqrt(evals)).T)
    return np.array(bases), np.array(whit)


def _kmat(x: np.ndarray, zero_skew: bool) -> np.ndarray:
    """K from its parameters (fx, fy, cx, cy[, skew])."""
    s = 0.0 if zero_skew else x[4]
    return np.array([[x[0], s, x[2]], [0, x[1], x[3]], [0, 0, 1.0]])


def refine_selfcal(
    k0: np.ndarray, tracks: list[list[Point]], *, zero_skew: bool = False,
) -> tuple[np.ndarray, dict[str, float], dict[str, float]]:
    """(K, std of its parameters, fit statistics) refined from the linear estimate `k0`."""
    n_img, n_dir = len(tracks), len(tracks[0])
    obs = np.array([[p.p for p in tr] for tr in tracks])
    bases, whit = _tangent_whiteners(tracks)
    nk = 4 if zero_skew else 5
    kinv = np.linalg.inv(k0)
    rvecs = []
    for i in range(1, n_img):
        h = homogeneous_homography(obs[0], obs[i])
        r = kinv @ h @ k0
        u, _, vt = np.linalg.svd(r / np.cbrt(np.linalg.det(r)))
        r = u @ vt
        rvecs.append(cv2.Rodrigues(r)[0].ravel())
    dirs = obs[0] @ kinv.T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs *= np.sign(dirs[:, 2:3] + 1e-300)
    ang = np.stack([np.arccos(np.clip(dirs[:, 2], -1, 1)), np.arctan2(dirs[:, 1], dirs[:, 0])], 1)
    kp = [k0[0, 0], k0[1, 1], k0[0, 2], k0[1, 2]] + ([] if zero_skew else [k0[0, 1]])
    x0 = np.concatenate([kp, np.ravel(rvecs), ang.ravel()])

    def residuals(x: np.ndarray) -> np.ndarray:
        k = _kmat(x[:nk], zero_skew)
        rots = [np.eye(3)] + [cv2.Rodrigues(x[nk + 3 * i: nk + 3 * i + 3])[0]
                              for i in range(n_img - 1)]
        a = x[nk + 3 * (n_img - 1):].reshape(n_dir, 2)
        d = np.stack([np.sin(a[:, 0]) * np.cos(a[:, 1]), np.sin(a[:, 0]) * np.sin(a[:, 1]),
                      np.cos(a[:, 0])], axis=1)
        pred = np.array([d @ (k @ r).T for r in rots]).reshape(-1, 3)
        pred /= np.linalg.norm(pred, axis=1, keepdims=True)
        o = obs.reshape(-1, 3)
        pred *= np.sign(np.sum(pred * o, axis=1, keepdims=True))
        t = np.einsum("nij,ni->nj", bases, pred - o)
        return np.einsum("nij,nj->ni", whit, t).ravel()

    sol = scipy.optimize.least_squares(residuals, x0, method="trf", x_scale="jac")
    dof = sol.fun.size - sol.x.size
    chi2 = float(sol.fun @ sol.fun)
    k = _kmat(sol.x[:nk], zero_skew)
    std: dict[str, float] = {}
    try:
        cov = np.linalg.pinv(sol.jac.T @ sol.jac, rcond=1e-12)[:nk, :nk]
        std = {p: float(np.sqrt(max(cov[i, i], 0))) for i, p in enumerate(PARAMS[:nk])}
        if zero_skew:
            std["skew"] = 0.0
    except np.linalg.LinAlgError:
        pass
    stats = {"chi2_per_dof": chi2 / dof if dof > 0 else float("nan"), "dof": int(dof),
             "converged": bool(sol.success)}
    return k, std, stats


def selfcal_intrinsics(
    tracks: list[list[Point]], image_size: tuple[int, int], *,
    zero_skew: bool = False, refine: bool = True, rng: np.random.Generator | None = None,
    mc_samples: int = _MC_SAMPLES,
) -> IntrinsicsEstimate:
    """K from vanishing points of the same >= 4 world directions in >= 3 images (Chang et al.).

    `tracks[i][d]` is direction d's vanishing point in image i. Every image pair gives
    one infinite homography; the paper's linear K (with skew) is then refined by maximum
    likelihood when the points carry covariances (`refine`, optionally `zero_skew`). How
    often the linear K K^T is not positive definite (and the linear std) come from Monte
    Carlo draws of the vanishing points; the refined std from the Gauss-Newton covariance.
    """
    if len(tracks) < 3:
        raise DegenerateError(f"self-calibration needs >= 3 images, got {len(tracks)}")
    ndir = {len(tr) for tr in tracks}
    if len(ndir) != 1 or min(ndir) < 4:
        raise DegenerateError(f"self-calibration needs the same >= 4 directions in every "
                              f"image, got {sorted(ndir)}")
    t = normalizer(image_size)
    vps = np.array([[p.p for p in tr] for tr in tracks])
    k = linear_selfcal(vps, t)
    rng = rng or np.random.default_rng(0)
    has_cov = any(np.any(p.cov) for tr in tracks for p in tr)

    def redraw(g: np.random.Generator) -> np.ndarray:
        drawn = np.array([[sample_points(p, 1, g)[0] for p in tr] for tr in tracks])
        return linear_selfcal(drawn, t)

    samples = mc_samples if has_cov else 0
    std, failed = monte_carlo_std(redraw, samples, rng) if samples else ({}, 0)
    stats: dict[str, Any] = {"mc_samples": samples, "mc_not_positive_definite": failed,
                             "directions": int(min(ndir)), "linear_camera_matrix": k.tolist(),
                             "linear_std": std, "refined": False}
    if refine and has_cov:
        k, std, fit = refine_selfcal(k, tracks, zero_skew=zero_skew)
        stats.update(fit, refined=True, zero_skew=zero_skew)
    return IntrinsicsEstimate(k, "selfcal", len(tracks), std, stats)
