"""Sub-pixel edges of bright quadrilaterals (the screen in a white flat frame, a card).

A quadrilateral is found by Otsu thresholding and contour approximation; each side is
then measured at sub-pixel precision: along the side, an intensity profile across the
edge is sampled from the raw image (bilinear) and the half-level crossing between the
local dark and bright levels gives one edge point; a weighted total-least-squares line
goes through the points (contrast^2 weights, 3-sigma rejection, one re-sampling along
the fitted line). Opposite sides meet at the rectangle's two vanishing points.
Assumes straight edges, i.e. negligible lens distortion (or an undistorted image).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.fit.classic.lines import Line, Point, fit_line, intersect
from calibration.fit.ransac import DegenerateError

_HALF_WIDTH_PX = 6.0  # profile half-length across an edge
_STEP_PX = 0.25  # profile sampling step
_END_MARGIN = 0.08  # fraction of each side left out near the corners
_MIN_SIDE_PX = 12.0


@dataclass(frozen=True)
class Quad:
    """A detected quadrilateral: sides 0..3 (corner k to corner k+1, clockwise on screen)."""

    sides: list[Line]
    corners: np.ndarray  # (4, 2) sub-pixel corners, intersections of adjacent sides

    def vanishing_points(self) -> tuple[Point, Point]:
        """(sides 0 & 2, sides 1 & 3): the vanishing points of the rectangle's two directions."""
        return intersect(self.sides[0], self.sides[2]), intersect(self.sides[1], self.sides[3])


def _ordered(corners: np.ndarray) -> np.ndarray:
    """Corners clockwise in the image (u right, v down) starting at the one nearest top-left."""
    c = corners.mean(axis=0)
    ang = np.arctan2(corners[:, 1] - c[1], corners[:, 0] - c[0])
    cw = corners[np.argsort(ang)]
    start = int(np.argmin(cw.sum(axis=1)))
    return np.roll(cw, -start, axis=0)


def _rough_quads(img: np.ndarray, count: int) -> list[np.ndarray]:
    """Corners (4, 2) of the `count` largest bright blobs, each approximated by a quadrilateral."""
    lo, hi = np.percentile(img, [1, 99.9])
    if hi - lo <= 0:
        raise DegenerateError("quadrilateral: the image is uniform (no bright screen or card)")
    u8 = np.clip((img - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
    u8 = cv2.GaussianBlur(u8, (5, 5), 1.0)
    _, mask = cv2.threshold(u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contours = sorted(contours, key=cv2.contourArea, reverse=True)[:count]
    if len(contours) < count:
        raise DegenerateError(f"quadrilateral: found {len(contours)} bright regions, "
                              f"expected {count}")
    out = []
    h, w = img.shape
    for k, cnt in enumerate(contours):
        xy = cnt.reshape(-1, 2)
        if xy.min() <= 1 or np.any(xy[:, 0] >= w - 2) or np.any(xy[:, 1] >= h - 2):
            raise DegenerateError(f"quadrilateral: bright region {k} touches the image border; "
                                  "the whole screen (card) must be in view")
        hull = cv2.convexHull(cnt)
        peri = cv2.arcLength(hull, True)
        for eps in (0.01, 0.02, 0.04, 0.06):
            approx = cv2.approxPolyDP(hull, eps * peri, True).reshape(-1, 2)
            if len(approx) == 4:
                break
        else:
            raise DegenerateError(f"quadrilateral: bright region {k} is not four-sided "
                                  f"({len(approx)} corners); is the whole screen in view?")
        out.append(_ordered(approx.astype(np.float64)))
    return out


def _edge_points(img: np.ndarray, a: np.ndarray, b: np.ndarray, inside: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel half-level crossings across the side a->b; (N, 2) points and contrast^2 weights."""
    length = float(np.linalg.norm(b - a))
    if length < _MIN_SIDE_PX:
        raise DegenerateError(f"quadrilateral: a side is only {length:.1f} px long")
    t = (b - a) / length
    n = np.array([t[1], -t[0]])
    if n @ (inside - a) > 0:
        n = -n  # n points outwards (to the dark side)
    s = np.linspace(_END_MARGIN, 1 - _END_MARGIN, max(int(length), 8)) * length
    o = np.arange(-_HALF_WIDTH_PX, _HALF_WIDTH_PX + 1e-9, _STEP_PX)
    base = a + s[:, None] * t
    grid = base[:, None, :] + o[None, :, None] * n
    prof = cv2.remap(img, grid[..., 0].astype(np.float32), grid[..., 1].astype(np.float32),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    quarter = len(o) // 4
    bright = np.median(prof[:, :quarter], axis=1)
    dark = np.median(prof[:, -quarter:], axis=1)
    contrast = bright - dark
    half = (bright + dark) / 2
    above = prof >= half[:, None]
    # last sample (from inside) still above half, followed by one below: the crossing
    falls = above[:, :-1] & ~above[:, 1:]
    has = falls.any(axis=1) & (contrast > 0.25 * np.max(contrast))
    idx = np.argmax(falls, axis=1)
    rows = np.arange(len(s))
    p0, p1 = prof[rows, idx], prof[rows, idx + 1]
    frac = (p0 - half) / np.where(p0 - p1 == 0, 1, p0 - p1)
    off = o[idx] + frac * _STEP_PX
    pts = base + off[:, None] * n
    return pts[has], contrast[has] ** 2


def _robust_line(pts: np.ndarray, w: np.ndarray) -> Line:
    """Line fit with two rounds of 3-sigma rejection of edge points."""
    keep = np.ones(len(pts), dtype=bool)
    line = fit_line(pts, w)
    for _ in range(2):
        res = np.abs(pts @ line.l[:2] + line.l[2])
        sig = 1.4826 * np.median(res[keep]) + 1e-6
        new = res < 3 * sig + 0.05
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
        line = fit_line(pts[keep], w[keep])
    return line  # weights are relative (contrast^2): the noise scale is from the residuals


def refine_quad(image: np.ndarray, corners: np.ndarray) -> Quad:
    """Sub-pixel sides and corners of a quadrilateral whose rough corners (4, 2) are known."""
    img = np.asarray(image, dtype=np.float32)
    inside = corners.mean(axis=0)
    sides: list[Line] = []
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        pts, w = _edge_points(img, a, b, inside)
        if len(pts) < 8:
            raise DegenerateError(f"quadrilateral: side {k} has no clear edge "
                                  f"({len(pts)} edge points)")
        sides.append(_robust_line(pts, w))
    # re-sample along the fitted sides (the rough corners can be a pixel or two off)
    rough = np.array([intersect(sides[k - 1], sides[k]).pixel() for k in range(4)])
    sides = []
    for k in range(4):
        pts, w = _edge_points(img, rough[k], rough[(k + 1) % 4], inside)
        if len(pts) < 8:
            raise DegenerateError(f"quadrilateral: side {k} has no clear edge")
        sides.append(_robust_line(pts, w))
    fine = np.array([intersect(sides[k - 1], sides[k]).pixel() for k in range(4)])
    return Quad(sides, fine)


def find_quads(image: np.ndarray, count: int = 1) -> list[Quad]:
    """The `count` largest bright quadrilaterals of a grey image, left to right."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"find_quads: expected a single-channel image, got shape {img.shape}")
    img = img.astype(np.float32)
    quads = [refine_quad(img, c) for c in _rough_quads(img, count)]
    return sorted(quads, key=lambda q: float(q.corners[:, 0].mean()))
