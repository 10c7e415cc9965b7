"""Quick intrinsics before (or without) decoding: the papers' closed-form methods on images
of bright rectangles (white flat frames of the screen, cards) or on decoded poses.

- rectangle (Lu & Whangbo's vanishing points): one rectangle per image, its two vanishing
  points, >= 4 images.
- selfcal (Chang, Wang & Wang's self-calibration): two non-parallel rectangles per image, the
  camera moving and turning freely, >= 3 images; the rectangles are matched left to right,
  sides top-first.
- rotation (Hartley): one fixed rectangle, a camera that only rotates (pan-tilt rig), >= 3.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.decode.frames_io import read_frames
from calibration.fit.classic.estimate import PARAMS, IntrinsicsEstimate, k_params, monte_carlo_std
from calibration.fit.classic.homography import fit_homography
from calibration.fit.classic.lines import Point, intersect, sample_points
from calibration.fit.classic.quad import Quad, find_quads
from calibration.fit.classic.rectangle import rectangle_intrinsics, vanishing_points
from calibration.fit.classic.rotation import interview_homographies, rotation_estimate
from calibration.fit.classic.selfcal import selfcal_intrinsics
from calibration.fit.correspondences import PointSet, point_set, subsample
from calibration.fit.ransac import DegenerateError
from calibration.models.blas_threads import single_thread_blas
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import FlatFrame, Plan, ScreenGeometry

METHODS = ("rectangle", "selfcal", "rotation")
_MAP_POINTS = 3000
_MC_SAMPLES = 200
_MAP_DRAWS = 40  # Monte Carlo refits per decoded pose


def white_flat_index(plan: Plan) -> int:
    """Plan index of the brightest flat frame (the screen as a bright quadrilateral)."""
    flats = [(f.level, i) for i, f in enumerate(plan.frames) if isinstance(f, FlatFrame)]
    if not flats:
        raise ValueError("plan has no flat frame to find the screen in")
    return max(flats)[1]


def read_white_flat(frames: str | Path, plan: Plan) -> np.ndarray:
    """The white flat frame of a captured pose (docs/formats.md frames: .npy stack or folder)."""
    src = read_frames(frames)
    index = white_flat_index(plan)
    if src.count <= index:
        raise ValueError(f"{frames}: has {src.count} frames, the white flat is frame {index}")
    if src.files:
        import cv2

        return cv2.imread(str(src.files[index]), cv2.IMREAD_UNCHANGED)
    return np.asarray(np.load(src.path, mmap_mode="r")[index])


def _aligned(ref: Quad, q: Quad) -> Quad:
    """`q` with its corners renumbered (cyclic shift) so that side k points like `ref`'s side k:
    the same physical side across images when the camera turns less than 45 deg about its axis."""
    def angles(x: Quad) -> np.ndarray:
        d = np.roll(x.corners, -1, axis=0) - x.corners
        return np.arctan2(d[:, 1], d[:, 0])

    a_ref, a_q = angles(ref), angles(q)
    cost = [np.sum(np.abs(np.angle(np.exp(1j * (np.roll(a_q, -s) - a_ref))))) for s in range(4)]
    s = int(np.argmin(cost))
    return Quad(q.sides[s:] + q.sides[:s], np.roll(q.corners, -s, axis=0))


def _quads(images: list[np.ndarray], count: int) -> list[list[Quad]]:
    """`count` quadrilaterals per image (left to right, sides matched to image 0's); errors
    name the image."""
    shapes = {np.shape(img) for img in images}
    if len(shapes) != 1:
        raise ValueError(f"images differ in size: {sorted(shapes)}; one camera resolution needed")
    out = []
    for i, img in enumerate(images):
        try:
            quads = find_quads(img, count)
        except DegenerateError as exc:
            raise DegenerateError(f"image {i}: {exc}") from None
        out.append(quads if not out else [_aligned(r, q) for r, q in zip(out[0], quads,
                                                                           strict=True)])
    return out


def _from_images(
    images: list[np.ndarray], method: str, *, square_pixels: bool = False,
    zero_skew: bool = False,
) -> IntrinsicsEstimate:
    """K from images of bright rectangles (white flats of the screen, cards) by `method`."""
    if method not in METHODS:
        raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    if not images:
        raise ValueError("no images given")
    h, w = np.shape(images[0])[:2]
    size = (int(w), int(h))
    if method == "rectangle":
        pairs = [q[0].vanishing_points() for q in _quads(images, 1)]
        est = rectangle_intrinsics(pairs, size, square_pixels=square_pixels)
    elif method == "selfcal":
        tracks = [[vp for q in qs for vp in q.vanishing_points()] for qs in _quads(images, 2)]
        est = selfcal_intrinsics(tracks, size, zero_skew=zero_skew)
    else:
        est = _rotation_from_quads([q[0] for q in _quads(images, 1)], size)
    est.stats["image_size"] = list(size)
    est.stats["source"] = "images"
    return est


def _rotation_from_quads(quads: list[Quad], size: tuple[int, int]) -> IntrinsicsEstimate:
    """Rotation-only K from the corners of one fixed rectangle; std by Monte Carlo on the
    corners (intersections of the fitted sides, with their covariances)."""
    pts = [[intersect(q.sides[k - 1], q.sides[k]) for k in range(4)] for q in quads]

    def solve(corners: list[np.ndarray]) -> np.ndarray:
        hs = [fit_homography(corners[0], c) for c in corners[1:]]
        return rotation_estimate(hs, size).k

    def redraw(g: np.random.Generator) -> np.ndarray:
        drawn = [np.array([sample_points(p, 1, g)[0] for p in qp]) for qp in pts]
        return solve([d[:, :2] / d[:, 2:] for d in drawn])

    est = rotation_estimate(
        [fit_homography(quads[0].corners, q.corners) for q in quads[1:]], size)
    est.std, failed = monte_carlo_std(redraw, _MC_SAMPLES, np.random.default_rng(0))
    est.stats.update(mc_samples=_MC_SAMPLES, mc_not_positive_definite=failed)
    return est


def _redrawn_homographies(pts: PointSet, draws: int, rng: np.random.Generator) -> np.ndarray:
    """(draws, 3, 3) homographies refitted with the decoded screen points redrawn from their
    sigma: the homography's (and its vanishing points') uncertainty by Monte Carlo."""
    out = np.empty((draws, 3, 3))
    pitch = np.asarray(pts.pitch_mm)
    for d in range(draws):
        noisy = (pts.screen_px + pts.sigma_px * rng.standard_normal(pts.sigma_px.shape)) * pitch
        out[d] = fit_homography(noisy, pts.pixels)
    return out


def _vps_with_cov(hm: np.ndarray, draws: np.ndarray) -> tuple[Point, Point]:
    """The homography's two vanishing points with covariances from the redrawn homographies."""
    out = []
    for col, base in zip((0, 1), vanishing_points(hm), strict=True):
        q = draws[:, :, col] / np.linalg.norm(draws[:, :, col], axis=1, keepdims=True)
        q *= np.sign(q @ base.p)[:, None]
        proj = np.eye(3) - np.outer(base.p, base.p)
        dev = (q - base.p) @ proj
        out.append(Point(base.p, dev.T @ dev / max(len(q) - 1, 1)))
    return out[0], out[1]


def _from_maps(
    maps: list[DecodedMaps], screen: ScreenGeometry, method: str, *,
    square_pixels: bool = False,
) -> IntrinsicsEstimate:
    """K from decoded poses of the screen: each pose's least-squares plane homography gives
    the screen's two vanishing points (rectangle) or, for a rotating camera, the
    image-to-image homographies (rotation). One plane has only two directions: no selfcal."""
    if method == "selfcal":
        raise ValueError("method selfcal needs two non-parallel rectangles in every image; "
                         "decoded poses of one screen give two directions. Use rectangle "
                         "(screen moved) or rotation (camera turned in place)")
    if method not in METHODS:
        raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    if not maps:
        raise ValueError("no decoded poses given")
    h, w = maps[0].shape
    rng = np.random.default_rng(0)
    hs, draws = [], []
    for i, m in enumerate(maps):
        pts = subsample(point_set(m, screen), _MAP_POINTS)
        if len(pts) < 8:
            raise DegenerateError(f"pose {i}: only {len(pts)} decoded points")
        hs.append(fit_homography(pts.screen_mm[:, :2], pts.pixels))
        draws.append(_redrawn_homographies(pts, _MAP_DRAWS, rng))
    if method == "rectangle":
        pairs = [_vps_with_cov(hm, d) for hm, d in zip(hs, draws, strict=True)]
        est = rectangle_intrinsics(pairs, (w, h), square_pixels=square_pixels)
    else:
        est = rotation_estimate(interview_homographies(hs), (w, h))
        ks = []
        for d in range(_MAP_DRAWS):
            try:
                ks.append(rotation_estimate(interview_homographies([x[d] for x in draws]),
                                            (w, h)).k)
            except DegenerateError:
                continue
        vals = np.array([[k_params(k)[p] for p in PARAMS] for k in ks])
        if len(ks) > 1:
            est.std = dict(zip(PARAMS, vals.std(axis=0, ddof=1).tolist(), strict=True))
        est.stats.update(mc_samples=_MAP_DRAWS, mc_not_positive_definite=_MAP_DRAWS - len(ks))
    est.stats["image_size"] = [int(w), int(h)]
    est.stats["source"] = "decoded maps"
    return est


def intrinsics_from_images(
    images: list[np.ndarray], method: str, *, square_pixels: bool = False,
    zero_skew: bool = False,
) -> IntrinsicsEstimate:
    """K from images of bright rectangles (white flats of the screen, cards) by `method`
    (module docstring). Small dense solves only: BLAS runs single-threaded."""
    with single_thread_blas():
        return _from_images(images, method, square_pixels=square_pixels, zero_skew=zero_skew)


def intrinsics_from_maps(
    maps: list[DecodedMaps], screen: ScreenGeometry, method: str, *,
    square_pixels: bool = False,
) -> IntrinsicsEstimate:
    """K from decoded poses (`rectangle` or `rotation`), with a Monte Carlo std from the
    decoded sigmas. BLAS runs single-threaded (small solves; threads only contend)."""
    with single_thread_blas():
        return _from_maps(maps, screen, method, square_pixels=square_pixels)
