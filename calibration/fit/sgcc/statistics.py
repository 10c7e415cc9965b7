"""Per-pose statistics of a converged sGCC fit: screen residuals (mm) mapped to camera pixels
through the inverse of the local Jacobian dQ/d(u, v), in `evaluate.per_pose_stats` layout.

The ray and its pixel derivatives do not depend on the pose, and the poses of a calibration
see mostly the same pixels: they are evaluated once per pixel of the poses' union, in row
blocks shared by all poses (threads over blocks), and each pose gathers its pixels' values.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from calibration.fit.observations import PoseObs
from calibration.models.sgcc import SGCCBase, expmap_jacobian_rows
from calibration.threads import map_in_threads

_BLOCK = 1 << 15  # union pixels per block: small temporaries


def _frame(model: SGCCBase, pixels: np.ndarray) -> np.ndarray:
    """Pose-independent rows (k, n) at pixels (n, 2): direction r (3), dr/du (3), dr/dv (3)
    [+ origin xy (2), its d/du (2), d/dv (2) for non-central models]."""
    comps, du, dv = model.components(pixels, derivatives=True)
    r, jr = expmap_jacobian_rows(comps[:, 0], comps[:, 1])
    rows = [r] + [jr[:, 0] * d[:, 0] + jr[:, 1] * d[:, 1] for d in (du, dv)]
    if model.n_components == 4:
        rows += [comps[:, 2:].T, du[:, 2:].T, dv[:, 2:].T]
    return np.concatenate(rows)


def _camera_px(
    rc: np.ndarray, tc: np.ndarray, f: np.ndarray, res: np.ndarray, sigma: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Screen residuals and sigmas (n, 2) mm of pixels with frame rows f (`_frame`) mapped to
    camera px in pose (rc, tc): px residuals (n, 2) and squared expected norms (n,).

    Feature-major closed form (no (n, 2, 2) stacks): the statistics pass over every pixel.
    """
    central = len(f) == 9
    r_s = rc @ f[:3]
    o_z = tc[2] if central else rc[2, :2] @ f[9:11] + tc[2]
    lam = -o_z / r_s[2]
    cols = []
    for k in range(2):
        dr = rc @ f[3 + 3 * k : 6 + 3 * k]
        do = np.zeros((3, 1)) if central else rc[:, :2] @ f[11 + 2 * k : 13 + 2 * k]
        dlam = -(do[2] + lam * dr[2]) / r_s[2]
        cols.append(do[:2] + lam * dr[:2] + dlam * r_s[:2])
    (j00, j10), (j01, j11) = cols
    det = j00 * j11 - j01 * j10
    px = np.empty_like(res)
    px[:, 0] = -(j11 * res[:, 0] - j01 * res[:, 1]) / det
    px[:, 1] = -(j00 * res[:, 1] - j10 * res[:, 0]) / det
    s0, s1 = sigma[:, 0], sigma[:, 1]
    expected2 = ((j11 * s0) ** 2 + (j01 * s1) ** 2 + (j10 * s0) ** 2 + (j00 * s1) ** 2) / det**2
    return px, expected2


def _flat_pixels(pixels: np.ndarray, size: tuple[int, int]) -> np.ndarray | None:
    """Raster indices of integer pixels inside the image, increasing (decoded maps); else None."""
    w, h = size
    u, v = pixels[:, 0], pixels[:, 1]
    if len(u) and not (np.array_equal(np.floor(u), u) and np.array_equal(np.floor(v), v)
                       and u.min() >= 0 and v.min() >= 0 and u.max() < w and v.max() < h):
        return None
    flat = v.astype(np.int64) * w + u.astype(np.int64)
    return flat if np.all(flat[1:] > flat[:-1]) else None


def fit_statistics(
    model: SGCCBase,
    rcs: Sequence[np.ndarray],
    tcs: Sequence[np.ndarray],
    obs: Sequence[PoseObs],
    residuals: Sequence[np.ndarray],
    inliers: Sequence[np.ndarray],
    pitch_mm: np.ndarray,
    dof_shrink: float = 1.0,
) -> list[tuple[np.ndarray, dict[str, Any]]]:
    """Camera-px residuals of each pose's inliers and its statistics row; `dof_shrink`
    (1 - parameters/residuals) scales the expected training residual."""
    idx = [np.flatnonzero(inl) for inl in inliers]
    flats = [_flat_pixels(ob.pixels[i], model.image_size) for ob, i in zip(obs, idx, strict=True)]
    px = [np.empty((len(i), 2)) for i in idx]
    sums = np.zeros((len(obs), 4))  # px^2, expected px^2, screen px^2 and its expectation

    def pose_part(j: int, sel: slice, f: np.ndarray) -> np.ndarray:
        """Camera px of inliers `sel` of pose j (frame rows f) into px[j]; their sums."""
        rows = idx[j][sel]
        r, sig = residuals[j][rows], obs[j].sigma_mm[rows]
        p, expected2 = _camera_px(rcs[j], tcs[j], f, r, sig)
        px[j][sel] = p
        return np.array([np.vdot(p, p), expected2.sum(), np.sum((r / pitch_mm) ** 2),
                         np.sum((sig / pitch_mm) ** 2)])

    if any(f is None for f in flats):  # not a decoded map's pixels: each pose on its own
        for j in range(len(obs)):
            for a in range(0, len(idx[j]), _BLOCK):
                sel = slice(a, a + _BLOCK)
                sums[j] += pose_part(j, sel, _frame(model, obs[j].pixels[idx[j][sel]]))
    else:
        for j, part in _shared_blocks(model, flats, pose_part):
            sums[j] += part
    out = []
    for j, (p, s) in enumerate(zip(px, sums, strict=True)):
        n = len(p)
        rms, expected, rms_screen, expected_screen = np.sqrt(
            s / max(n, 1) * [1.0, dof_shrink, 1.0, dof_shrink]
        ).tolist()
        out.append((p, {
            "rms_px": rms,
            "expected_rms_px": expected,
            "rms_screen_px": rms_screen,
            "expected_rms_screen_px": expected_screen,
            "noise_floor_ratio": rms / expected if expected > 0 else float("nan"),
            "n_points": n,
            "n_outliers": len(inliers[j]) - n,
            "outlier_fraction": 1.0 - n / max(len(inliers[j]), 1),
        }))
    return out


def _shared_blocks(
    model: SGCCBase, flats: list[np.ndarray],
    pose_part: Callable[[int, slice, np.ndarray], np.ndarray],
) -> list[tuple[int, np.ndarray]]:
    """(pose, `pose_part(pose, sel, frame)`) of every pose's inliers, the frame evaluated once
    per pixel of the poses' union, in raster blocks (threads over blocks, disjoint slices)."""
    w, h = model.image_size
    seen = np.zeros(w * h, dtype=bool)
    for f in flats:
        seen[f] = True
    union = np.flatnonzero(seen)
    where = np.empty(w * h, dtype=np.int64)
    where[union] = np.arange(len(union))
    blocks = [(a, min(a + _BLOCK, len(union))) for a in range(0, len(union), _BLOCK)]

    def block(bounds: tuple[int, int]) -> list[tuple[int, np.ndarray]]:
        """The union pixels [a, b): their frame, then each pose's pixels among them."""
        a, b = bounds
        pix = union[a:b]
        frame = _frame(model, np.stack([pix % w, pix // w], axis=1).astype(np.float64))
        parts = []
        for j, f in enumerate(flats):
            lo, hi = np.searchsorted(f, [pix[0], pix[-1] + 1]).tolist()
            if hi > lo:
                same = hi - lo == b - a  # then the pose saw every union pixel of the block
                parts.append((j, pose_part(j, slice(lo, hi),
                                           frame if same else frame[:, where[f[lo:hi]] - a])))
        return parts

    return [part for parts in map_in_threads(block, blocks) for part in parts]
