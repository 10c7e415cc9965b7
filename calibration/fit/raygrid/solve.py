"""Raygrid numerics: table-node observations, closed-form rays, pose refinement, the joint
Gauss-Newton step (Schur complement over the per-pixel ray blocks) and ray covariances."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calibration.models.raygrid import RayGridModel
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import ScreenGeometry

_CHUNK = 65536
_POSE_GN_STEPS = 3
_MIN_POSES_PER_RAY = 2


@dataclass
class Observations:
    """Table-node data over poses: screen points S (J,M,2) mm, sigmas (J,M,2) mm, valid (J,M)."""

    pixels: np.ndarray  # (M, 2) node pixels (u, v)
    screen: np.ndarray
    sigma: np.ndarray
    valid: np.ndarray


def node_observations(
    maps: Sequence[DecodedMaps], screen: ScreenGeometry, step: int
) -> Observations:
    """Screen points (mm) and sigmas of every pose at the table-node pixels."""
    pitch = np.asarray(screen.pitch_mm, dtype=np.float64)
    h, w = maps[0].shape
    vv, uu = np.meshgrid(np.arange(0, h, step), np.arange(0, w, step), indexing="ij")
    scr = np.stack([np.stack([m.x[::step, ::step], m.y[::step, ::step]], -1) for m in maps])
    sig = np.stack(
        [np.stack([m.sigma_x[::step, ::step], m.sigma_y[::step, ::step]], -1) for m in maps]
    ).astype(np.float64)
    mask = np.stack([m.mask[::step, ::step] for m in maps])
    scr = scr.reshape(len(maps), -1, 2) * pitch
    sig = sig.reshape(len(maps), -1, 2) * pitch
    valid = mask.reshape(len(maps), -1)
    valid &= np.all(np.isfinite(scr), axis=2) & np.all(np.isfinite(sig) & (sig > 0), axis=2)
    scr[~valid] = 0.0
    sig[~valid] = 1.0
    pix = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
    return Observations(pix, scr, sig, valid)


def _perp_basis(d: np.ndarray) -> np.ndarray:
    """Orthonormal basis (M, 3, 2) of the plane perpendicular to each unit vector d (M, 3)."""
    ref = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(d, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.stack([e1, np.cross(d, e1)], axis=2)


def _intersect(
    rc: np.ndarray, tc: np.ndarray, o: np.ndarray, d: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rays (M,3) in each pose's screen frame (J,M,3), their z = 0 hits Q, depth λ, d_s."""
    o_s = np.einsum("jab,mb->jma", rc, o) + tc[:, None, :]
    d_s = np.einsum("jab,mb->jma", rc, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -o_s[..., 2] / d_s[..., 2]
    return o_s + lam[..., None] * d_s, lam, d_s, o_s


def _proj_rows(d_s: np.ndarray) -> np.ndarray:
    """First two rows of P = I - d_s e_z^T / d_sz (J,M,2,3): dQ = P (do_s + λ dd_s)."""
    p = np.zeros((*d_s.shape[:2], 2, 3))
    p[..., 0, 0] = 1.0
    p[..., 1, 1] = 1.0
    p[..., :, 2] = -d_s[..., :2] / d_s[..., 2:3]
    return p


def _residuals(
    rc: np.ndarray, tc: np.ndarray, o: np.ndarray, d: np.ndarray, ob: Observations, sl: slice
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals (J,M,2), usable mask, Q, λ and d_s for pixel slice `sl`."""
    q, lam, d_s, _ = _intersect(rc, tc, o, d)
    usable = ob.valid[:, sl] & np.isfinite(lam) & (lam > 0)
    e = np.where(usable[..., None], (q[..., :2] - ob.screen[:, sl]) / ob.sigma[:, sl], 0.0)
    return e, usable, q, lam, d_s


def _consensus(x: np.ndarray, w: np.ndarray, ob: Observations, cut: float) -> np.ndarray:
    """Weights with gross outliers zeroed: points far from their node's median direction.

    Far = beyond max(5.9 x the median deviation over all points, `cut` x the point's own
    angular sigma). With 3+ poses one wild point per node is caught; with 2 it cannot be
    told apart and the later residual cut drops the node.
    """
    u = x / np.linalg.norm(x, axis=2, keepdims=True)
    with warnings.catch_warnings():  # nodes seen in no pose: all-NaN median, NaN is right
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(np.where((w > 0)[..., None], u, np.nan), axis=0)
    med /= np.linalg.norm(med, axis=1, keepdims=True)
    ang = np.arccos(np.clip(np.sum(u * med[None], axis=2), -1.0, 1.0))
    used = (w > 0) & np.isfinite(ang)
    if not used.any():
        return w
    scale = float(np.median(ang[used]))
    own = cut * np.max(ob.sigma, axis=2) / np.linalg.norm(x, axis=2)
    return np.where(used & (ang <= np.maximum(5.9 * scale, own)), w, 0.0)


def initial_rays(
    rc: np.ndarray, tc: np.ndarray, ob: Observations, w: np.ndarray, central: bool, cut: float
) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form (weighted TLS) rays of all nodes from their camera-frame 3D screen points."""
    r = np.transpose(rc, (0, 2, 1))  # screen -> camera
    t = -np.einsum("jab,jb->ja", r, tc)
    x = np.einsum("jab,jmb->jma", r[:, :, :2], ob.screen) + t[:, None, :]
    w = _consensus(x, w, ob, cut) / np.mean(ob.sigma**2, axis=2)
    wsum = np.maximum(w.sum(axis=0), 1e-300)
    if central:
        centroid = np.zeros((x.shape[1], 3))
    else:
        centroid = np.einsum("jm,jma->ma", w, x) / wsum[:, None]
    xc = x - centroid
    xm = np.swapaxes(xc, 0, 1)  # (M, J, 3)
    scatter = np.swapaxes(xm * w.T[..., None], 1, 2) @ xm
    _, vec = np.linalg.eigh(scatter)
    d = vec[:, :, 2]
    d *= np.sign(np.einsum("jm,jma,ma->m", w, x, d) + 1e-300)[:, None]
    o = centroid - np.sum(centroid * d, axis=1, keepdims=True) * d
    return o, d


def refine_poses(
    rc: np.ndarray, tc: np.ndarray, o: np.ndarray, d: np.ndarray, ob: Observations, w: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Camera->screen poses (J,3,3), (J,3) by Gauss-Newton with the rays fixed."""
    rc, tc = rc.copy(), tc.copy()
    covered = np.all(np.isfinite(d), axis=1)
    o0, d0 = np.where(covered[:, None], o, 0.0), np.where(covered[:, None], d, 1.0)
    for _ in range(_POSE_GN_STEPS):
        a = np.zeros((len(rc), 6, 6))
        b = np.zeros((len(rc), 6))
        for start in range(0, len(d0), _CHUNK):
            sl = slice(start, start + _CHUNK)
            e, usable, q, _, d_s = _residuals(rc, tc, o0[sl], d0[sl], ob, sl)
            p = _proj_rows(d_s)
            jac = np.concatenate(
                [np.cross((q - tc[:, None, :])[:, :, None, :], p), p], axis=3
            )
            jac = jac / ob.sigma[:, sl, :, None]
            ww = np.where(usable & covered[sl], w[:, sl], 0.0)
            a += np.einsum("jm,jmak,jmal->jkl", ww, jac, jac)
            b += np.einsum("jm,jmak,jma->jk", ww, jac, e)
        step = -np.linalg.solve(a, b[..., None])[..., 0]
        for j in range(len(rc)):
            rc[j] = cv2.Rodrigues(step[j, :3])[0] @ rc[j]
        tc += step[:, 3:]
    return rc, tc


@dataclass
class JointSystem:
    """Normal equations of one pixel chunk: ray blocks, ray-pose coupling, pose blocks."""

    arr: np.ndarray  # (M, k, k)
    br: np.ndarray  # (M, k)
    arp: np.ndarray  # (M, k, 6J)
    app: np.ndarray  # (6J, 6J)
    bp: np.ndarray  # (6J,)


def _joint_chunk(
    rc: np.ndarray,
    tc: np.ndarray,
    o: np.ndarray,
    d: np.ndarray,
    ob: Observations,
    w: np.ndarray,
    sl: slice,
    central: bool,
) -> JointSystem:
    """Gauss-Newton normal equations of rays (pixel slice `sl`) and all poses jointly."""
    e, usable, q, lam, d_s = _residuals(rc, tc, o, d, ob, sl)
    p = _proj_rows(d_s)  # (J, M, 2, 3)
    prce = p @ (rc[:, None] @ _perp_basis(d)[None])  # (J, M, 2, 2)
    jr = lam[..., None, None] * prce
    if not central:
        jr = np.concatenate([jr, prce], axis=3)
    # d(R^T-row a . Q)/d(omega) = -(p_a x (Q - t))^T: rotation columns by cross products.
    rot = np.cross((q - tc[:, None, :])[:, :, None, :], p)
    jp = np.concatenate([rot, p], axis=3)  # (J, M, 2, 6)
    scale = np.where(usable, w[:, sl], 0.0)[..., None, None] / ob.sigma[:, sl, :, None]
    jr, jp = jr * scale, jp * scale
    n_pose, n_pix, k = len(rc), len(d), jr.shape[3]
    jr_t = np.swapaxes(jr, 2, 3)  # (J, M, k, 2)
    arp = np.transpose(jr_t @ jp, (1, 2, 0, 3)).reshape(n_pix, k, 6 * n_pose)
    jp_flat = jp.reshape(n_pose, -1, 6)
    e_flat = e.reshape(n_pose, -1)
    app_blocks = np.swapaxes(jp_flat, 1, 2) @ jp_flat
    app = np.zeros((6 * n_pose, 6 * n_pose))
    for j in range(n_pose):
        app[6 * j : 6 * j + 6, 6 * j : 6 * j + 6] = app_blocks[j]
    return JointSystem(
        np.sum(jr_t @ jr, axis=0),
        np.sum(jr_t @ e[..., None], axis=0)[..., 0],
        arp,
        app,
        (np.swapaxes(jp_flat, 1, 2) @ e_flat[..., None]).ravel(),
    )


def _safe_inv(a: np.ndarray) -> np.ndarray:
    """Inverses of stacked (M,k,k) matrices; zero where singular (pixels without a ray)."""
    out = np.zeros_like(a)
    ok = np.all(np.isfinite(a), axis=(1, 2))
    ok[ok] = np.abs(np.linalg.det(a[ok])) > 1e-300
    out[ok] = np.linalg.inv(a[ok])
    return out


def _gauge_pinv(s: np.ndarray, rel: float = 1e-10) -> tuple[np.ndarray, int]:
    """Pseudo-inverse of the reduced pose system (Jacobi-scaled), dropping gauge directions."""
    scale = 1.0 / np.sqrt(np.maximum(np.diag(s), 1e-300))
    val, vec = np.linalg.eigh(s * scale[:, None] * scale[None, :])
    keep = val > rel * val[-1]
    inv = (vec[:, keep] / val[keep]) @ vec[:, keep].T
    return inv * scale[:, None] * scale[None, :], int((~keep).sum())


def _reduced(
    rc: np.ndarray, tc: np.ndarray, o: np.ndarray, d: np.ndarray, ob: Observations,
    w: np.ndarray, central: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Schur complement (6J,6J) of the ray blocks and its right-hand side."""
    n = 6 * len(rc)
    s, rhs = np.zeros((n, n)), np.zeros(n)
    for start in range(0, len(d), _CHUNK):
        sl = slice(start, start + _CHUNK)
        js = _joint_chunk(rc, tc, o[sl], d[sl], ob, w, sl, central)
        inv = _safe_inv(js.arr)
        tmp = (inv @ js.arp).reshape(-1, n)
        s += js.app - js.arp.reshape(-1, n).T @ tmp
        rhs += js.bp - tmp.T @ js.br.ravel()
    return s, rhs


def joint_step(
    rc: np.ndarray, tc: np.ndarray, o: np.ndarray, d: np.ndarray, ob: Observations,
    w: np.ndarray, central: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One Gauss-Newton step on all rays and poses together (rays eliminated by Schur)."""
    covered = np.all(np.isfinite(d), axis=1)
    o0, d0 = np.where(covered[:, None], o, 0.0), np.where(covered[:, None], d, [[0, 0, 1.0]])
    wc = np.where(covered[None, :], w, 0.0)
    s, rhs = _reduced(rc, tc, o0, d0, ob, wc, central)
    sinv, _ = _gauge_pinv(s)
    dp = -sinv @ rhs
    o_new, d_new = o0.copy(), d0.copy()
    for start in range(0, len(d0), _CHUNK):
        sl = slice(start, start + _CHUNK)
        js = _joint_chunk(rc, tc, o0[sl], d0[sl], ob, wc, sl, central)
        dr = -np.einsum("mkl,ml->mk", _safe_inv(js.arr), js.br + js.arp @ dp)
        basis = _perp_basis(d0[sl])
        dn = d0[sl] + np.einsum("mak,mk->ma", basis, dr[:, :2])
        dn /= np.linalg.norm(dn, axis=1, keepdims=True)
        if not central:
            on = o0[sl] + np.einsum("mak,mk->ma", basis, dr[:, 2:])
            o_new[sl] = on - np.sum(on * dn, axis=1, keepdims=True) * dn
        d_new[sl] = dn
    rc_new, tc_new = rc.copy(), tc.copy()
    for j in range(len(rc)):
        rc_new[j] = cv2.Rodrigues(dp[6 * j : 6 * j + 3])[0] @ rc[j]
        tc_new[j] = tc[j] + dp[6 * j + 3 : 6 * j + 6]
    o_new[~covered], d_new[~covered] = np.nan, np.nan
    return rc_new, tc_new, o_new, d_new


def ray_covariance(
    rc: np.ndarray, tc: np.ndarray, o: np.ndarray, d: np.ndarray, ob: Observations,
    w: np.ndarray, central: bool,
) -> tuple[np.ndarray, int]:
    """Per-pixel ray covariance (M,k,k) including pose uncertainty (gauge projected out)."""
    covered = np.all(np.isfinite(d), axis=1)
    o0, d0 = np.where(covered[:, None], o, 0.0), np.where(covered[:, None], d, [[0, 0, 1.0]])
    wc = np.where(covered[None, :], w, 0.0)
    s, _ = _reduced(rc, tc, o0, d0, ob, wc, central)
    sinv, dropped = _gauge_pinv(s)
    k = 2 if central else 4
    cov = np.full((len(d0), k, k), np.nan)
    for start in range(0, len(d0), _CHUNK):
        sl = slice(start, start + _CHUNK)
        js = _joint_chunk(rc, tc, o0[sl], d0[sl], ob, wc, sl, central)
        inv = _safe_inv(js.arr)
        g = inv @ js.arp
        gs = (g.reshape(-1, g.shape[2]) @ sinv).reshape(g.shape)
        cov[sl] = inv + gs @ np.swapaxes(g, 1, 2)
    cov[~covered] = np.nan
    return cov, dropped


def cost_and_inliers(
    rc: np.ndarray, tc: np.ndarray, o: np.ndarray, d: np.ndarray, ob: Observations, cut: float
) -> tuple[float, np.ndarray, np.ndarray]:
    """Total whitened cost, inlier mask (J,M) and residuals (J,M,2) mm at the current state."""
    covered = np.all(np.isfinite(d), axis=1)
    o0, d0 = np.where(covered[:, None], o, 0.0), np.where(covered[:, None], d, 1.0)
    e, usable, q, _, _ = _residuals(rc, tc, o0, d0, ob, slice(None))
    usable &= covered[None, :]
    norm = np.linalg.norm(e, axis=2)
    med = float(np.median(norm[usable])) if usable.any() else 0.0
    inl = usable & (norm <= max(cut, 5.9 * med))
    return float(np.sum(norm[inl] ** 2)), inl, q[..., :2] - ob.screen


def ray_weights(ob: Observations, inl: np.ndarray) -> np.ndarray:
    """Per (pose, node) weight of the whitened residuals: 1 for inliers, 0 otherwise."""
    return np.where(inl & ob.valid, 1.0, 0.0)


def mask_sparse(o: np.ndarray, d: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """NaN rays for nodes with fewer than 2 contributing poses."""
    few = np.count_nonzero(w > 0, axis=0) < _MIN_POSES_PER_RAY
    o, d = o.copy(), d.copy()
    o[few] = np.nan
    d[few] = np.nan
    return o, d


def pixel_residuals(
    model: RayGridModel,
    rc: np.ndarray,
    tc: np.ndarray,
    pix: np.ndarray,
    res_mm: np.ndarray,
    sigma_mm: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Screen-plane residuals (N,2) mm at pixels in camera px via the local Jacobian, and the
    expected squared residual (N,) of each point's noise (sigma mm) in camera px."""
    o, odu, odv, d, ddu, ddv = model.rays_with_derivatives(pix)
    o_s, d_s = o @ rc.T + tc, d @ rc.T
    lam = -o_s[:, 2] / d_s[:, 2]
    p = _proj_rows(d_s[None])[0]
    cols = [
        np.einsum("nab,nb->na", p, do @ rc.T + lam[:, None] * (dd @ rc.T))
        for do, dd in ((odu, ddu), (odv, ddv))
    ]
    jinv = _safe_inv(np.stack(cols, axis=2))
    bad = ~np.any(jinv != 0, axis=(1, 2))
    px = -np.einsum("nab,nb->na", jinv, res_mm)
    expected2 = np.einsum("nab,nb->n", jinv**2, sigma_mm**2)
    px[bad], expected2[bad] = np.nan, np.nan
    return px, expected2
