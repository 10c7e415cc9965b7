"""Initial sGCC state from a parametric (OpenCV rational) fit, moved into the sGCC gauge."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from calibration.fit.observations import PoseObs
from calibration.fit.sgcc.lm import gauge_constraints
from calibration.fit.sgcc.state import LMState
from calibration.models.blas_threads import single_thread_blas
from calibration.models.bspline import SplineGrid
from calibration.models.sgcc import logmap

_INIT_POINTS_PER_POSE = 1000  # plenty for 14 + 6/pose parameters; the LM refits everything
_INIT_FIT_POINTS = 40000
_REJECT_FACTOR = 5.0


def _subsample(n: int, k: int) -> np.ndarray:
    """Evenly spread indices of at most k out of n."""
    return np.unique(np.linspace(0, n - 1, min(n, k)).astype(np.int64))


OpenCVFit = tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]


def opencv_init(obs: list[PoseObs], image_size: tuple[int, int]) -> OpenCVFit:
    """(K, dist, rvecs, tvecs) of OpenCV's rational model on subsampled points, refitted
    without gross outliers: the start of every sGCC fit."""
    objs, imgs = [], []
    for o in obs:
        sel = _subsample(len(o.pixels), _INIT_POINTS_PER_POSE)
        obj = np.zeros((sel.size, 3), np.float32)
        obj[:, :2] = o.screen_mm[sel]
        objs.append(obj)
        imgs.append(o.pixels[sel].astype(np.float32))
    flags = cv2.CALIB_RATIONAL_MODEL
    for _ in range(2):
        _, k, dist, rvecs, tvecs = _calibrate_one_thread(objs, imgs, image_size, flags)
        keep_o, keep_i = [], []
        for obj, img, rv, tv in zip(objs, imgs, rvecs, tvecs, strict=True):
            proj, _ = cv2.projectPoints(obj, rv, tv, k, dist)
            err = np.linalg.norm(proj[:, 0, :] - img, axis=1)
            good = err <= _REJECT_FACTOR * max(float(np.median(err)), 1e-3)
            keep_o.append(obj[good])
            keep_i.append(img[good])
        objs, imgs = keep_o, keep_i
    return k, dist, list(rvecs), list(tvecs)


def _calibrate_one_thread(
    objs: list[np.ndarray], imgs: list[np.ndarray], image_size: tuple[int, int], flags: int
) -> tuple:
    """cv2.calibrateCamera with OpenCV's thread pool and its bundled BLAS at one thread.

    Why: on a loaded 2-core machine their threads contend; two calls took 11-16 s instead
    of ~1 s in the non-central test under load. The thread count is restored afterwards.
    """
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with single_thread_blas():
            return cv2.calibrateCamera(objs, imgs, image_size, None, None, flags=flags)
    finally:
        cv2.setNumThreads(before)


def _directions(k: np.ndarray, dist: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Unit ray directions of pixels (N,2) under an OpenCV model."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    xy = cv2.undistortPoints(
        pixels.reshape(-1, 1, 2).astype(np.float64), k, dist, None, None, None, crit
    )
    d = np.concatenate([xy[:, 0, :], np.ones((len(pixels), 1))], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _unique_rows(pix: np.ndarray) -> np.ndarray:
    """np.unique(pix, axis=0) (rows sorted by column 0, then 1) by one lexsort: several
    times faster than unique's structured-row sort."""
    p = pix[np.lexsort((pix[:, 1], pix[:, 0]))]
    keep = np.ones(len(p), dtype=bool)
    keep[1:] = np.any(p[1:] != p[:-1], axis=1)
    return p[keep]


def gauge_rotation(center_dir: np.ndarray, du_dir: np.ndarray) -> np.ndarray:
    """Rotation Q with Q c = +z and Q (du) in the x-z plane (x > 0): the sGCC rotation gauge."""
    e3 = center_dir / np.linalg.norm(center_dir)
    e1 = du_dir - (du_dir @ e3) * e3
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(e3, e1), e3])


def initial_state(
    obs: list[PoseObs], grid: SplineGrid, n_comp: int, cv_fit: OpenCVFit | None = None
) -> LMState:
    """Central ray field and poses from OpenCV's rational model (`cv_fit`, computed from obs
    when None), rotated into the sGCC gauge. Single-threaded BLAS: the solves are small."""
    with single_thread_blas():
        return _initial_state(obs, grid, n_comp, cv_fit)


def _initial_state(
    obs: list[PoseObs], grid: SplineGrid, n_comp: int, cv_fit: OpenCVFit | None
) -> LMState:
    """Body of `initial_state`."""
    k, dist, rvecs, tvecs = opencv_init(obs, grid.image_size) if cv_fit is None else cv_fit
    w, h = grid.image_size
    c = np.array([[(w - 1) / 2, (h - 1) / 2], [(w - 1) / 2 + 1.0, (h - 1) / 2]])
    dc = _directions(k, dist, c)
    q = gauge_rotation(dc[0], dc[1] - dc[0])
    pix = np.concatenate([o.pixels[_subsample(len(o.pixels), _INIT_FIT_POINTS)] for o in obs])
    pix = _unique_rows(pix)  # poses overlap: fit each pixel once
    pix = pix[_subsample(len(pix), _INIT_FIT_POINTS)]
    ab = logmap(_directions(k, dist, pix) @ q.T)
    coeffs = np.zeros((grid.size, n_comp))
    coeffs[:, :2] = grid.fit(pix[:, 0], pix[:, 1], ab)
    cons = gauge_constraints(grid, n_comp, grid.size * n_comp)
    x = coeffs.ravel()
    x -= cons.T @ np.linalg.solve(cons @ cons.T, cons @ x)
    rcs, tcs = [], []
    for rv, tv in zip(rvecs, tvecs, strict=True):
        r = q @ cv2.Rodrigues(rv)[0]
        t = q @ np.asarray(tv, dtype=np.float64).ravel()
        rcs.append(r.T)
        tcs.append(-r.T @ t)
    return LMState(x.reshape(grid.size, n_comp), rcs, tcs)


def pose_from_model(
    model_unproject: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], ob: PoseObs
) -> tuple[np.ndarray, np.ndarray]:
    """Camera->screen (Rc, tc) of one pose from a fitted model's rays, by PnP on normalized rays."""
    _, d = model_unproject(ob.pixels)
    ok = d[:, 2] > 1e-6
    img = (d[ok, :2] / d[ok, 2:3]).astype(np.float64)
    obj = np.zeros((int(ok.sum()), 3))
    obj[:, :2] = ob.screen_mm[ok]
    sel = _subsample(len(obj), _INIT_POINTS_PER_POSE)
    found, rv, tv, _ = cv2.solvePnPRansac(
        obj[sel], img[sel], np.eye(3), None, reprojectionError=1e-3, iterationsCount=200
    )
    if not found:
        raise ValueError("held-out pose: PnP found no pose consistent with the model's rays")
    r = cv2.Rodrigues(rv)[0]
    t = np.asarray(tv, dtype=np.float64).ravel()
    return r.T, -r.T @ t
