"""Per-pixel ray uncertainty: parametric models from their Fisher information, sGCC from its
own covariance; also the information a planned pose would add (for pose guidance).

Parametric: the weighted Jacobian of every pose's projections over (model, pose) parameters
gives the normal matrix; the poses are marginalized out (Schur complement), so the model's
covariance is `inv(sum_j A_j - B_j C_j^-1 B_j^T)`, the same weighting as `param_std`. A
pixel's ray sigma is `sqrt(trace(J_d cov J_d^T))`, J_d the derivative of its unit ray
direction over the model parameters (numerical, central differences).

"The worst predicted ray sigma" of a model and its poses is one figure, `worst_ray_sigma`,
read by the report and by pose guidance alike: the largest ray sigma on the
`RAY_SIGMA_GRID` sensor grid among the pixels whose ray is within `MAX_FIELD_ANGLE_DEG` of
the optical axis (where a whole screen can be shown at all), each training pose counted with
at most `RAY_SIGMA_POINTS_PER_POSE` points.
"""

from __future__ import annotations

import cv2
import numpy as np

from calibration.evaluate import screen_jacobian
from calibration.fit.correspondences import PointSet, subsample
from calibration.models.base import CameraModel
from calibration.models.sgcc import SGCCBase

_POSE_PARAMS = 6
RAY_SIGMA_GRID = (48, 36)  # (nx, ny) sensor grid of the ray-sigma map
RAY_SIGMA_POINTS_PER_POSE = 800  # points per training pose counted in the information
MIN_POLE_MARGIN = 0.25  # radial factor's numerator and denominator stay this far from 0
MAX_FIELD_ANGLE_DEG = 70.0  # the worst sigma is taken over pixels this close to the axis


def sensor_grid(image_size: tuple[int, int], nx: int = 40, ny: int = 30) -> np.ndarray:
    """(ny*nx, 2) pixel centres of an even grid over the sensor (corners included)."""
    w, h = image_size
    uu, vv = np.meshgrid(np.linspace(0, w - 1, nx), np.linspace(0, h - 1, ny))
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def free_parameters(model: CameraModel, param_std: dict[str, float] | None) -> np.ndarray:
    """Indices of the fitted parameters: those with a non-zero std in the fit's `param_std`."""
    names = model.param_names() if hasattr(model, "param_names") else []
    n = model.get_params().size
    if not param_std or len(names) != n:
        return np.arange(n)
    return np.array([i for i, k in enumerate(names) if param_std.get(k, 1.0) != 0.0], np.int64)


def _project(model: CameraModel, rvec: np.ndarray, tvec: np.ndarray,
             screen_mm: np.ndarray) -> np.ndarray:
    rot = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    return model.project(screen_mm @ rot.T + tvec)


def camera_sigma(model: CameraModel, rotation: np.ndarray, translation: np.ndarray,
                 points: PointSet) -> np.ndarray:
    """(N,) expected isotropic camera-px sigma of each point (decoded sigma pushed forward)."""
    jac = screen_jacobian(model, rotation, translation, points)
    return np.sqrt(0.5 * np.einsum("nij,nj,nij->n", jac, points.sigma_px**2, jac))


def pose_information(model: CameraModel, rotation: np.ndarray, translation: np.ndarray,
                     points: PointSet, free: np.ndarray) -> np.ndarray:
    """Information (p, p) on the model's free parameters from one pose, its pose marginalized."""
    base = model.get_params()
    rvec = cv2.Rodrigues(np.asarray(rotation, np.float64))[0].ravel()
    tvec = np.asarray(translation, np.float64).ravel()
    s = points.screen_mm
    weight = np.repeat(1.0 / camera_sigma(model, rotation, translation, points), 2)
    cols = []
    try:
        for i in free:
            step = 1e-6 * max(abs(base[i]), 1e-3)
            v = base.copy()
            v[i] += step
            model.set_params(v)
            plus = _project(model, rvec, tvec, s)
            v[i] -= 2 * step
            model.set_params(v)
            cols.append((plus - _project(model, rvec, tvec, s)).ravel() / (2 * step))
    finally:
        model.set_params(base)
    pose = np.concatenate([rvec, tvec])
    for k in range(_POSE_PARAMS):
        step = 1e-6 if k < 3 else 1e-3 * max(abs(pose[k]), 1.0)
        p, m = pose.copy(), pose.copy()
        p[k] += step
        m[k] -= step
        cols.append((_project(model, p[:3], p[3:], s) - _project(model, m[:3], m[3:], s)).ravel()
                    / (2 * step))
    jac = np.stack(cols, axis=1) * weight[:, None]
    jac = jac[np.all(np.isfinite(jac), axis=1)]
    normal = jac.T @ jac
    npar = len(free)
    a, b, c = normal[:npar, :npar], normal[:npar, npar:], normal[npar:, npar:]
    return a - b @ np.linalg.solve(c, b.T)


def covariance(information: np.ndarray) -> np.ndarray:
    """Inverse of an information matrix, scaled for conditioning (inf where singular)."""
    scale = np.sqrt(np.clip(np.diag(information), 1e-300, None))
    try:
        inv = np.linalg.inv(information / np.outer(scale, scale))
    except np.linalg.LinAlgError:
        return np.full_like(information, np.inf)
    return inv / np.outer(scale, scale)


def direction_jacobian(model: CameraModel, pixels: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(N, 3, p) derivative of each pixel's unit ray direction over the free parameters."""
    base = model.get_params()
    out = np.empty((len(pixels), 3, len(free)))
    try:
        for col, i in enumerate(free):
            step = 1e-6 * max(abs(base[i]), 1e-3)
            v = base.copy()
            v[i] += step
            model.set_params(v)
            _, plus = model.unproject(pixels)
            v[i] -= 2 * step
            model.set_params(v)
            _, minus = model.unproject(pixels)
            out[:, :, col] = (plus - minus) / (2 * step)
    finally:
        model.set_params(base)
    return out


def ray_sigma(jd: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(N,) 1-sigma ray direction angle (rad) from `direction_jacobian` and a covariance."""
    var = np.einsum("nap,pq,naq->n", jd, cov, jd)
    return np.sqrt(np.clip(var, 0.0, None))


def rotation_matrices(directions: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """(N, 3, 3) A with omega x d = A @ omega for each direction d (A = -[d]x); zero where
    not `ok`, so those pixels take no part in the rotation's least squares."""
    d = np.where(ok[:, None], directions, 0.0)
    a = np.zeros((len(d), 3, 3))
    a[:, 0, 1], a[:, 0, 2] = d[:, 2], -d[:, 1]
    a[:, 1, 0], a[:, 1, 2] = -d[:, 2], d[:, 0]
    a[:, 2, 0], a[:, 2, 1] = d[:, 1], -d[:, 0]
    return a


def spline_ray_sigma_without_rotation(model: SGCCBase, pixels: np.ndarray,
                                      chunk: int = 4096) -> np.ndarray:
    """(N,) ray sigma (rad) of an sGCC model from its coefficient covariance, without what a
    rotation of every ray explains: `without_rotation` on its sparse direction Jacobian
    (`direction_jacobian`: 16 controls per pixel), never forming the dense pixels x
    coefficients matrix; pixels are taken `chunk` at a time.

    With J the Jacobian, S the covariance, A the pixels' rotation matrices and R the
    rotation fitted to J over all pixels, the variance of J - A R is
    J S J' - 2 J (S R') A' + A (R S R') A', each term local to the pixel's controls."""
    cov = model.covariance
    c = model.n_components
    npar = cov.shape[0]
    _, d = model.unproject(pixels)
    jac, idx, w = model.direction_jacobian(pixels)
    ok = np.isfinite(d).all(axis=1) & np.isfinite(jac).all(axis=(1, 2))
    a = rotation_matrices(d, ok)
    jac = np.where(ok[:, None, None], jac, 0.0)
    cols = (idx[:, :, None] * c + np.arange(2)).reshape(len(idx), -1)  # (N, 32) direction cols
    rhs = np.zeros((3, npar))  # sum over pixels of A' J
    for s in range(0, len(idx), chunk):
        g = np.einsum("nai,nab->nib", a[s:s + chunk], jac[s:s + chunk])  # (n, 3, 2)
        vals = g[:, :, None, :] * w[s:s + chunk, None, :, None]  # (n, 3, 16, 2)
        for i in range(3):
            rhs[i] += np.bincount(cols[s:s + chunk].ravel(), vals[:, i].reshape(-1),
                                  minlength=npar)
    rotation = np.linalg.lstsq(np.einsum("nai,naj->ij", a, a), rhs, rcond=None)[0]  # (3, P)
    cov_rt = cov @ rotation.T  # (P, 3)
    rsr = rotation @ cov_rt  # (3, 3)
    var = np.empty(len(idx))
    for s in range(0, len(idx), chunk):
        sl = slice(s, s + chunk)
        comp = model.component_covariance(pixels[sl])[:, :2, :2]
        whole = np.einsum("nab,nbc,nac->n", jac[sl], comp, jac[sl])
        local = (cov_rt[cols[sl]].reshape(-1, 16, 2, 3) * w[sl, :, None, None]).sum(axis=1)
        cross = np.einsum("nab,nbj,naj->n", jac[sl], local, a[sl])  # trace(J S R' A')
        rot = np.einsum("nij,jk,nik->n", a[sl], rsr, a[sl])
        var[sl] = whole - 2 * cross + rot
    out = np.sqrt(np.clip(var, 0.0, None))
    out[~ok] = np.nan
    return out


def without_rotation(jd: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """`jd` with the part a rigid rotation of all rays explains taken out (least squares over
    the pixels with a finite ray). Two fits compared after their best rotation differ only in
    the rest, so that rest is the uncertainty a comparison can be judged against: a fit's
    rotation-like error (which, with the poses free, is much of its ray sigma) is no error of
    the lens model."""
    ok = np.isfinite(directions).all(axis=1) & np.isfinite(jd).all(axis=(1, 2))
    a = rotation_matrices(directions, ok)
    j = np.where(ok[:, None, None], jd, 0.0)
    normal = np.einsum("nai,naj->ij", a, a)
    rotation = np.linalg.lstsq(normal, np.einsum("nai,nap->ip", a, j), rcond=None)[0]
    return jd - np.einsum("nai,ip->nap", a, rotation)


def parametric_ray_sigma(model: CameraModel, poses: list[tuple[np.ndarray, np.ndarray]],
                         points: list[PointSet], pixels: np.ndarray, free: np.ndarray,
                         chi2: float = 1.0, rotation_free: bool = False) -> np.ndarray:
    """(N,) ray sigma (rad) at `pixels` of a parametric fit to `points` seen from `poses`;
    `rotation_free`: without what a rotation of every ray explains (`without_rotation`)."""
    info = sum(pose_information(model, r, t, p, free) for (r, t), p in zip(poses, points,
                                                                              strict=True))
    jd = direction_jacobian(model, pixels, free)
    if rotation_free:
        jd = without_rotation(jd, model.unproject(pixels)[1])
    return ray_sigma(jd, covariance(info) * chi2)


def model_ray_sigma(model: CameraModel, pixels: np.ndarray,
                    poses: list[tuple[np.ndarray, np.ndarray]] | None = None,
                    points: list[PointSet] | None = None,
                    param_std: dict[str, float] | None = None,
                    rotation_free: bool = False) -> tuple[np.ndarray, str]:
    """Ray sigma (rad) at pixels and how it was obtained: sGCC covariance or parametric Fisher;
    `rotation_free` leaves out what a rotation of every ray explains."""
    if hasattr(model, "ray_std") and getattr(model, "covariance", None) is not None:
        if rotation_free:
            return (spline_ray_sigma_without_rotation(model, pixels),
                    "sGCC full coefficient covariance, rotation of every ray taken out")
        ang, _ = model.ray_std(pixels)
        return ang, "sGCC full coefficient covariance"
    if poses and points and hasattr(model, "param_names"):
        free = free_parameters(model, param_std)
        return (parametric_ray_sigma(model, poses, points, pixels, free,
                                     rotation_free=rotation_free),
                f"parametric Fisher information ({len(free)} model parameters, "
                f"{len(poses)} poses marginalized"
                + (", rotation of every ray taken out)" if rotation_free else ")"))
    return np.full(len(pixels), np.nan), "not available for this model"


def reachable(model: CameraModel, pixels: np.ndarray,
              max_angle_deg: float = MAX_FIELD_ANGLE_DEG) -> np.ndarray:
    """(N,) pixels whose ray is within `max_angle_deg` of the optical axis: where a whole
    screen can be seen at all (a wide-angle lens's corners near 90 degrees never see one)."""
    _, d = model.unproject(pixels)
    with np.errstate(invalid="ignore"):
        return np.isfinite(d).all(axis=1) & (d[:, 2] >= np.cos(np.radians(max_angle_deg)))


def worst_ray_sigma(model: CameraModel, pixels: np.ndarray, sigma: np.ndarray) -> float:
    """The worst predicted ray sigma (rad): the largest `sigma` at `pixels` within
    `MAX_FIELD_ANGLE_DEG` of the axis (nan when none is finite there)."""
    vals = sigma[reachable(model, pixels) & np.isfinite(sigma)]
    return float(vals.max()) if vals.size else float("nan")


def ray_sigma_map(model: CameraModel, poses: list[tuple[np.ndarray, np.ndarray]],
                  points: list[PointSet], param_std: dict[str, float] | None = None,
                  rotation_free: bool = False) -> tuple[np.ndarray, np.ndarray, str]:
    """The predicted ray-sigma map of a fit: (`RAY_SIGMA_GRID` pixels (N, 2), sigma (N,) rad,
    how it was obtained), each training pose's `points` counted with at most
    `RAY_SIGMA_POINTS_PER_POSE` of them; `worst_ray_sigma` reads its figure."""
    grid = sensor_grid(model.image_size, *RAY_SIGMA_GRID)
    small = [subsample(p, RAY_SIGMA_POINTS_PER_POSE) for p in points]
    sigma, method = model_ray_sigma(model, grid, poses, small, param_std, rotation_free)
    return grid, sigma, method


def radial_pole_margin(model: CameraModel) -> float:
    """How far a rational radial factor `(1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + ...)`
    stays from 0/0 over the image: the smaller of its numerator's and denominator's least
    magnitude for radii up to the image's corners (inf for other models).

    Its six coefficients are nearly redundant (a common factor cancels), so a fit can land
    where both nearly vanish inside the image; the rays there are still fitted, but a
    first-order ray sigma is not meaningful near that pair (it can read 1e7 urad where the
    ray is right to 1e2).
    """
    if getattr(model, "type_name", "") != "opencv-rational":
        return float("inf")
    k = np.asarray(model.dist, np.float64)
    grid = sensor_grid(model.image_size, 9, 7)
    x = (grid[:, 0] - model.cx) / model.fx
    y = (grid[:, 1] - model.cy) / model.fy
    r2 = np.linspace(0.0, 1.2 * float(np.max(x * x + y * y)), 400)
    num = 1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))
    den = 1 + r2 * (k[5] + r2 * (k[6] + r2 * k[7]))
    return float(min(np.abs(num).min(), np.abs(den).min()))
