"""A printed chessboard seen by a simulated camera: 8-bit images with known truth.

Rays are cast from the truth camera to the board (averaged over each pixel's area), which
may be bowed: a point (x, y) of the board's frame lies at
z = bow_x (xi^2 - 1/3) + bow_y (eta^2 - 1/3), xi and eta running over [-1, 1] across the
inner-corner extent (the convention phasecal's target-shape fit reports; written here on
its own so a mistake cannot hide on both sides of a test). The board is black and white
squares on a white margin one square wide, in front of a grey background; the image is
blurred (Gaussian), scaled to DN, given Gaussian noise and quantized to 8 bits.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from hw_mocks.camera_base import TruthCamera

_INTERSECT_ITERS = 8  # fixed point on the bowed surface: the bow's slope is ~1e-2


@dataclass(frozen=True)
class BoardTruth:
    """The printed board: COLSxROWS inner corners, square side and bow (mm)."""

    cols: int
    rows: int
    square_mm: float
    bow_x_mm: float = 0.0
    bow_y_mm: float = 0.0

    def depth(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """z (mm, board frame) of the board surface at (x, y)."""
        hx, hy = (self.cols - 1) * self.square_mm / 2, (self.rows - 1) * self.square_mm / 2
        xi, eta = (x - hx) / hx, (y - hy) / hy
        return self.bow_x_mm * (xi * xi - 1 / 3) + self.bow_y_mm * (eta * eta - 1 / 3)

    def corners(self) -> np.ndarray:
        """(N, 3) inner corners on the bowed surface, row-major (x fastest), mm."""
        gx, gy = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        x, y = gx.ravel() * self.square_mm, gy.ravel() * self.square_mm
        return np.stack([x, y, self.depth(x, y)], axis=1)

    def reflectance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Reflectance in [0, 1] at board points: squares, white margin, grey outside."""
        s = self.square_mm
        i, j = np.floor(x / s), np.floor(y / s)
        on_squares = (i >= -1) & (i <= self.cols - 1) & (j >= -1) & (j <= self.rows - 1)
        on_margin = (i >= -2) & (i <= self.cols) & (j >= -2) & (j <= self.rows)
        black = ((i + j) % 2 == 0) & on_squares
        return np.where(black, 0.0, np.where(on_margin, 1.0, 0.45))


@dataclass(frozen=True)
class BoardPose:
    """Board frame to camera frame: X_cam = R X_board + t (mm)."""

    rotation: np.ndarray
    translation: np.ndarray


def look_at_poses(board: BoardTruth, count: int, distance_mm: float, seed: int = 0,
                  max_tilt_deg: float = 35.0) -> list[BoardPose]:
    """`count` poses of the board's centre in front of the camera at about `distance_mm`,
    tilted up to `max_tilt_deg` about random axes and shifted across the view."""
    rng = np.random.default_rng(seed)
    centre = np.array([(board.cols - 1) * board.square_mm / 2,
                       (board.rows - 1) * board.square_mm / 2, 0.0])
    poses = []
    for k in range(count):
        axis = rng.normal(size=2)
        axis /= np.linalg.norm(axis)
        tilt = np.radians(max_tilt_deg) * (0.4 + 0.6 * (k % 3) / 2) * rng.choice([-1, 1])
        rot = cv2.Rodrigues(np.array([axis[0], axis[1], 0.0]) * tilt)[0]
        roll = cv2.Rodrigues(np.array([0.0, 0.0, rng.uniform(-0.3, 0.3)]))[0]
        rot = rot @ roll
        shift = np.array([rng.uniform(-0.12, 0.12), rng.uniform(-0.1, 0.1), 0.0]) * distance_mm
        t = shift + np.array([0.0, 0.0, distance_mm * rng.uniform(0.9, 1.1)]) - rot @ centre
        poses.append(BoardPose(rot, t))
    return poses


class BoardRenderer:
    """Renders boards for one camera. The camera's rays through the pixels' corners are cast
    once; inside a pixel the board point is interpolated bilinearly between its corners (the
    mapping is smooth on that scale), so a `supersample`^2 area average costs no more rays."""

    def __init__(self, camera: TruthCamera) -> None:
        self.camera = camera
        w, h = camera.width, camera.height
        uu, vv = np.meshgrid(np.arange(w + 1) - 0.5, np.arange(h + 1) - 0.5)
        origins, dirs = camera.rays(uu, vv)
        self.origins, self.dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)

    def _board_points(self, board: BoardTruth, pose: BoardPose) -> np.ndarray:
        """(H+1, W+1, 2) board (x, y) mm where each pixel-corner ray meets the board; NaN
        where it does not (behind the camera, or the camera has no ray)."""
        rt = pose.rotation.T
        o = (self.origins - pose.translation) @ rt.T
        d = self.dirs @ rt.T
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -o[:, 2] / d[:, 2]
            for _ in range(_INTERSECT_ITERS):
                p = o + s[:, None] * d
                s = (board.depth(p[:, 0], p[:, 1]) - o[:, 2]) / d[:, 2]
        p = o + s[:, None] * d
        p[~(s > 0)] = np.nan
        h, w = self.camera.height, self.camera.width
        return p[:, :2].reshape(h + 1, w + 1, 2)

    def render(self, board: BoardTruth, pose: BoardPose, *, blur_px: float = 0.7,
               noise_dn: float = 1.5, black_dn: float = 25.0, white_dn: float = 215.0,
               supersample: int = 4, seed: int = 0) -> np.ndarray:
        """The board as an 8-bit (H, W) image seen from `pose`."""
        c = self._board_points(board, pose)
        c00, c10, c01, c11 = c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]
        img = np.zeros(c00.shape[:2])
        offs = (np.arange(supersample) + 0.5) / supersample
        for a in offs:
            for b in offs:
                p = (c00 * (1 - a) * (1 - b) + c10 * a * (1 - b) + c01 * (1 - a) * b
                     + c11 * a * b)
                img += board.reflectance(p[..., 0], p[..., 1])
        img = np.where(np.isfinite(img), img / supersample**2, 0.45)
        if blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_px)
        dn = black_dn + (white_dn - black_dn) * img
        dn += np.random.default_rng(seed).normal(0.0, noise_dn, dn.shape)
        return np.clip(np.rint(dn), 0, 255).astype(np.uint8)


def true_corner_pixels(camera: TruthCamera, board: BoardTruth, pose: BoardPose) -> np.ndarray:
    """(N, 2) where the camera images the board's inner corners (the detector's truth)."""
    pts = board.corners() @ pose.rotation.T + pose.translation
    return camera.project(pts)
