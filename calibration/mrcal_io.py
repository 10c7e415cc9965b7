"""mrcal `.cameramodel` files: exact for the OpenCV family, a splined-stereographic fit to the
rays of other central models (its residual reported), and reading OpenCV-family files back.

The splined model is evaluated here exactly as mrcal 2.2 does (mrcal.c,
`_project_point_splined`): u = 2 xy / (|p| + z) (stereographic), q = (u + Δ(u)) f + c, with
Δ a uniform cubic B-spline surface whose knots are spaced so that Nx - 3 intervals span
fov_x_deg. Δ is linear in its control points, so the fit is a linear least-squares problem.
"""

from __future__ import annotations

import ast
import math
from pathlib import Path
from typing import Any

import numpy as np
from scipy.sparse import csr_matrix

from calibration.models.base import CameraModel, ModelError
from calibration.models.parametric import (
    OpenCV5Model,
    OpenCVRationalModel,
    PinholeFamily,
)

SPLINE_ORDER = 3
DEFAULT_NX = 16  # knots across the field of view (mrcal's own examples use 16-30)
_FIT_STEP_PX = 4.0
_SMOOTH = 1e-6  # weight of the second-difference regularization of the control points


def _opencv_lensmodel(model: PinholeFamily) -> tuple[str, np.ndarray]:
    """mrcal lens model name and distortion vector of an OpenCV-family model."""
    if model.type_name == "opencv5":
        return "LENSMODEL_OPENCV5", model.dist[:5]
    if model.type_name == "opencv-rational":
        if np.any(model.dist[8:] != 0):
            return "LENSMODEL_OPENCV12", model.dist[:12]
        return "LENSMODEL_OPENCV8", model.dist[:8]
    raise ModelError(
        f"mrcal export: {model.type_name!r} has no exact mrcal 2.2 lens model (mrcal has no "
        "equidistant/Kannala-Brandt model); pass approximate=true (CLI --approximate) for a "
        "splined-stereographic fit with its residual reported")


def splined_name(nx: int, ny: int, fov_x_deg: int) -> str:
    """mrcal's lens model string for a cubic splined stereographic model."""
    return (f"LENSMODEL_SPLINED_STEREOGRAPHIC_order={SPLINE_ORDER}_Nx={nx}_Ny={ny}"
            f"_fov_x_deg={int(fov_x_deg)}")


def stereographic(d: np.ndarray) -> np.ndarray:
    """Normalized stereographic coordinates u (N,2) of directions or points (N,3)."""
    mag = np.linalg.norm(d, axis=1)
    return d[:, :2] * (2.0 / (mag + d[:, 2]))[:, None]


def _segments_per_u(nx: int, fov_x_deg: float) -> float:
    u_edge = math.tan(math.radians(fov_x_deg) / 4.0) * 2.0
    return (nx - 1 - 2) / (2.0 * u_edge)


def _bspline_weights(t: np.ndarray) -> np.ndarray:
    """The 4 uniform cubic B-spline weights (N,4) at t in [0,1) (mrcal's get_sample_coeffs)."""
    t2, t3 = t * t, t * t * t
    return np.stack([(-t3 + 3 * t2 - 3 * t + 1) / 6, (1.5 * t3 - 3 * t2 + 2) / 3,
                     (-3 * t3 + 3 * t2 + 3 * t + 1) / 6, t3 / 6], axis=1)


def spline_design(u: np.ndarray, nx: int, ny: int, fov_x_deg: float) -> csr_matrix:
    """Sparse (N, Nx*Ny) matrix of B-spline weights: Δ(u) = A @ controls (Nx*Ny, 2)."""
    spu = _segments_per_u(nx, fov_x_deg)
    ix = u[:, 0] * spu + (nx - 1) / 2.0
    iy = u[:, 1] * spu + (ny - 1) / 2.0
    ix0 = np.clip(np.floor(ix).astype(int), 1, nx - 3)
    iy0 = np.clip(np.floor(iy).astype(int), 1, ny - 3)
    wx, wy = _bspline_weights(ix - ix0), _bspline_weights(iy - iy0)
    n = len(u)
    rows = np.repeat(np.arange(n), 16)
    cols = ((iy0[:, None, None] - 1 + np.arange(4)[None, :, None]) * nx
            + (ix0[:, None, None] - 1 + np.arange(4)[None, None, :])).reshape(n, 16)
    vals = (wy[:, :, None] * wx[:, None, :]).reshape(n, 16)
    return csr_matrix((vals.ravel(), (rows, cols.ravel())), shape=(n, nx * ny))


def project_splined(points: np.ndarray, intrinsics: np.ndarray, nx: int, ny: int,
                    fov_x_deg: float) -> np.ndarray:
    """Pixels (N,2) of points (N,3) through a cubic splined-stereographic model (mrcal's math)."""
    u = stereographic(np.asarray(points, dtype=np.float64))
    ctrl = np.asarray(intrinsics[4:], dtype=np.float64).reshape(ny * nx, 2)
    delta = spline_design(u, nx, ny, fov_x_deg) @ ctrl
    return (u + delta) * np.asarray(intrinsics[:2]) + np.asarray(intrinsics[2:4])


def _pixel_grid(size: tuple[int, int], step: float, offset: float = 0.0) -> np.ndarray:
    w, h = size
    uu, vv = np.meshgrid(np.arange(offset, w, step), np.arange(offset, h, step))
    return np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)


def _second_differences(nx: int, ny: int) -> csr_matrix:
    """Second differences of an (ny, nx) control grid along x and y (regularization rows)."""
    idx = np.arange(nx * ny).reshape(ny, nx)
    trip = [(idx[:, :-2], idx[:, 1:-1], idx[:, 2:]), (idx[:-2], idx[1:-1], idx[2:])]
    rows, cols, vals, r = [], [], [], 0
    for a, b, c in trip:
        m = a.size
        for arr, v in ((a, 1.0), (b, -2.0), (c, 1.0)):
            rows.append(np.arange(r, r + m))
            cols.append(arr.ravel())
            vals.append(np.full(m, v))
        r += m
    return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(r, nx * ny))


def fit_splined(model: CameraModel, nx: int = DEFAULT_NX) -> dict[str, Any]:
    """Cubic splined-stereographic intrinsics fitted to a central model's rays.

    Pixels of a 4-px grid are unprojected; f and c come from a linear fit of pixel to
    stereographic u, the control points from linear least squares (weak second-difference
    regularization fills knots outside the image). The residual is measured on a grid
    offset by 2 px (pixels not used in the fit). Returns lensmodel, intrinsics and stats.
    """
    if not model.is_central:
        raise ModelError(f"mrcal export: {model.type_name!r} is non-central; a .cameramodel "
                         "(mrcal 2.2) describes central cameras only")
    pix = _pixel_grid(model.image_size, _FIT_STEP_PX)
    _, d = model.unproject(pix)
    ok = np.all(np.isfinite(d), axis=1) & (d[:, 2] > -0.9)
    if ok.sum() < 100:
        raise ModelError("mrcal export: fewer than 100 pixels with rays to fit a spline to")
    pix, u = pix[ok], stereographic(d[ok])
    umax = np.abs(u).max(axis=0) * 1.02
    if not np.all(umax > 1e-3):
        raise ModelError("mrcal export: the model's rays span almost no angle; nothing to fit")
    fov_x_deg = math.ceil(math.degrees(4 * math.atan(umax[0] / 2)))  # mrcal: an integer
    spu = _segments_per_u(nx, fov_x_deg)
    ny = max(4, math.ceil(2 * umax[1] * spu) + 3)
    f, c = np.empty(2), np.empty(2)
    for k in range(2):
        a = np.stack([u[:, k], np.ones(len(u))], axis=1)
        f[k], c[k] = np.linalg.lstsq(a, pix[:, k], rcond=None)[0]
    target = (pix - c) / f - u
    a = spline_design(u, nx, ny, fov_x_deg)
    reg = _second_differences(nx, ny)
    normal = (a.T @ a + _SMOOTH * len(u) / (nx * ny) * (reg.T @ reg)).toarray()
    ctrl = np.linalg.solve(normal, a.T @ target)
    intrinsics = np.concatenate([f, c, ctrl.ravel()])
    check = _pixel_grid(model.image_size, _FIT_STEP_PX, offset=_FIT_STEP_PX / 2)
    _, dc = model.unproject(check)
    okc = np.all(np.isfinite(dc), axis=1) & (dc[:, 2] > -0.9)
    err = np.linalg.norm(project_splined(dc[okc], intrinsics, nx, ny, fov_x_deg) - check[okc],
                         axis=1)
    return {
        "lensmodel": splined_name(nx, ny, fov_x_deg),
        "intrinsics": intrinsics,
        "residual": {"rms_px": float(np.sqrt(np.mean(err**2))), "max_px": float(err.max()),
                     "median_px": float(np.median(err)), "n_pixels": int(okc.sum())},
    }


def cameramodel_text(model: CameraModel, *, approximate: bool = False,
                     nx: int = DEFAULT_NX, extrinsics: np.ndarray | None = None
                     ) -> tuple[str, dict[str, Any]]:
    """(.cameramodel text, info) for a model: exact for the OpenCV family, else a spline fit.

    info: `lensmodel`, `exact` and for the spline fit its `residual` (px). Generic central
    models are always fitted; the fisheye model only with `approximate` (there is no exact
    mrcal form and the fit must be asked for knowingly). `extrinsics`: mrcal's rt_fromref
    (rotation vector rad, t mm; X_cam = R X_ref + t) of a rig's camera; default: the camera
    frame is the reference.
    """
    info: dict[str, Any]
    if isinstance(model, OpenCV5Model | OpenCVRationalModel):
        name, dist = _opencv_lensmodel(model)
        intr = np.concatenate([[model.fx, model.fy, model.cx, model.cy], dist])
        info = {"lensmodel": name, "exact": True}
        header = f"# phasecal {model.type_name} model, exact\n"
    else:
        if isinstance(model, PinholeFamily) and not approximate:
            _opencv_lensmodel(model)  # raises with the reason
        fit = fit_splined(model, nx)
        name, intr = fit["lensmodel"], fit["intrinsics"]
        info = {"lensmodel": name, "exact": False, "residual": fit["residual"]}
        r = fit["residual"]
        header = (f"# phasecal {model.type_name} model approximated by mrcal's splined "
                  f"stereographic model:\n# residual RMS {r['rms_px']:.4g} px, max "
                  f"{r['max_px']:.4g} px over {r['n_pixels']} pixels\n")
    vals = ", ".join(repr(float(v)) for v in intr)
    w, h = model.image_size
    if extrinsics is None:
        rt_note, rt = "the camera frame is the reference", "0.0, 0.0, 0.0, 0.0, 0.0, 0.0"
    else:
        rt_note = "rotation vector (rad) and translation (mm) from the rig's reference frame"
        rt = ", ".join(repr(float(v)) for v in np.asarray(extrinsics, dtype=np.float64))
    text = (f"{header}{{\n    'lensmodel':  '{name}',\n"
            f"    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....\n"
            f"    'intrinsics': [ {vals} ],\n"
            f"    # extrinsics are rt_fromref: {rt_note}\n"
            f"    'extrinsics': [ {rt} ],\n"
            f"    'imagersize': [ {w}, {h} ],\n}}\n")
    return text, info


_FROM_MRCAL = {"LENSMODEL_PINHOLE": (OpenCV5Model, 0), "LENSMODEL_OPENCV4": (OpenCV5Model, 4),
               "LENSMODEL_OPENCV5": (OpenCV5Model, 5),
               "LENSMODEL_OPENCV8": (OpenCVRationalModel, 8),
               "LENSMODEL_OPENCV12": (OpenCVRationalModel, 12)}


def read_cameramodel(path: str | Path) -> PinholeFamily:
    """An OpenCV-family phasecal model from a .cameramodel file (intrinsics; extrinsics ignored)."""
    return read_cameramodel_with_extrinsics(path)[0]


def read_cameramodel_with_extrinsics(path: str | Path) -> tuple[PinholeFamily, np.ndarray]:
    """(model, rt_fromref (6,): rotation vector rad, t mm) of a .cameramodel file."""
    p = Path(path)
    try:
        data = ast.literal_eval(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ModelError(f"{p}: file not found") from None
    except (SyntaxError, ValueError) as exc:
        raise ModelError(f"{p}: not a .cameramodel (Python dict literal): {exc}") from None
    if not isinstance(data, dict):
        raise ModelError(f"{p}: expected a dict with lensmodel, intrinsics, imagersize")
    name = data.get("lensmodel")
    if name not in _FROM_MRCAL:
        raise ModelError(f"{p}: lensmodel {name!r} has no phasecal equivalent; readable: "
                         f"{sorted(_FROM_MRCAL)}")
    cls, nd = _FROM_MRCAL[name]
    intr, size = data.get("intrinsics"), data.get("imagersize")
    if not (isinstance(intr, list | tuple) and len(intr) == 4 + nd):
        raise ModelError(f"{p}: intrinsics: expected {4 + nd} numbers for {name}")
    if not (isinstance(size, list | tuple) and len(size) == 2):
        raise ModelError(f"{p}: imagersize: expected [W, H]")
    fx, fy, cx, cy = (float(v) for v in intr[:4])
    k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    model = cls((int(size[0]), int(size[1])), k, np.asarray(intr[4:], dtype=np.float64))
    model.stats = {"source": str(p), "lensmodel": name}
    rt = data.get("extrinsics", [0.0] * 6)
    if not (isinstance(rt, list | tuple) and len(rt) == 6):
        raise ModelError(f"{p}: extrinsics: expected 6 numbers (rt_fromref)")
    return model, np.asarray(rt, dtype=np.float64)
