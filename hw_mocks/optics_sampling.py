"""Blurring a screen image and sampling it at fixed sub-pixel screen points, fast and exact.

cv2.remap would quantize sample positions to 1/32 px (a phase error comparable to the
noise of a good decode), so the bilinear taps are computed here from float64 positions
once per setup. Images that vary along one axis only (cosine patterns, flats) take a
separable path: a Gaussian blur and a bilinear interpolation of a product f(x) g(y) are
the products of their 1-D versions, so a frame costs two gathers from short lines.
"""

from __future__ import annotations

import cv2
import numpy as np

from calibration.shared.plan import ScreenGeometry


def gaussian_kernel(sigma: float) -> np.ndarray:
    """Normalized sampled Gaussian (float64) reaching +-4 sigma; [1.0] for sigma == 0."""
    if sigma <= 0:
        return np.ones(1)
    half = int(np.ceil(4 * sigma))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    return k / k.sum()


def _blur_line(line: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """1-D blur with a dark (zero) surround beyond the screen's edge."""
    if kernel.size == 1:
        return line.astype(np.float32)
    half = kernel.size // 2  # "full" then slice: also right when the kernel outgrows the line
    full = np.convolve(line.astype(np.float64), kernel, mode="full")
    return full[half : half + line.size].astype(np.float32)


def _padded_line(line: np.ndarray) -> np.ndarray:
    """Edge-replicated line (length n + 2) followed by two zeros for off-screen samples."""
    line = np.asarray(line, dtype=np.float32)
    return np.concatenate([line[:1], line, line[-1:], np.zeros(2, np.float32)])


class ScreenSampler:
    """Blurred screen image -> mean of bilinear samples over each camera pixel's sub-samples."""

    def __init__(
        self,
        x: np.ndarray,
        y: np.ndarray,
        screen: ScreenGeometry,
        supersample: int,
        blur_sigma_px: float,
    ) -> None:
        """x, y: (H*s, W*s) screen px of every sub-sample (NaN: off the screen)."""
        self.screen = screen
        self.supersample = supersample
        self.shape = (x.shape[0] // supersample, x.shape[1] // supersample)
        self.kernel = gaussian_kernel(blur_sigma_px)
        wp, hp = screen.width_px + 2, screen.height_px + 2
        ok = np.isfinite(x) & np.isfinite(y)
        xp = np.where(ok, x, 0.0) + 1.0  # padded coordinates, in [0.5, W + 0.5]
        yp = np.where(ok, y, 0.0) + 1.0
        x0 = np.clip(np.floor(xp), 0, wp - 2)
        y0 = np.clip(np.floor(yp), 0, hp - 2)
        # Off-screen samples point at the zeros after each padded line, with weight 0.
        self.x0 = np.where(ok, x0, wp).astype(np.int32)
        self.y0 = np.where(ok, y0, hp).astype(np.int32)
        self.fx = np.where(ok, xp - x0, 0.0).astype(np.float32)
        self.fy = np.where(ok, yp - y0, 0.0).astype(np.float32)
        # Blurred all-ones lines: the dark surround's share along each axis (separable path).
        self._ones_x = self._ones_y = None
        if self.kernel.size > 1:
            ones_x = _blur_line(np.ones(screen.width_px), self.kernel)
            ones_y = _blur_line(np.ones(screen.height_px), self.kernel)
            self._ones_x = self._lerp(_padded_line(ones_x), self.x0, self.fx)
            self._ones_y = self._lerp(_padded_line(ones_y), self.y0, self.fy)

    @staticmethod
    def _lerp(padded: np.ndarray, i0: np.ndarray, f: np.ndarray) -> np.ndarray:
        """Linear interpolation of a padded line at integer taps i0 with fractions f."""
        a = np.take(padded, i0)
        return a + f * (np.take(padded[1:], i0) - a)

    def _checked(self, image: np.ndarray) -> np.ndarray:
        """The image as float32, after checking it has the screen's shape."""
        img = np.asarray(image, dtype=np.float32)
        expected = (self.screen.height_px, self.screen.width_px)
        if img.shape != expected:
            raise ValueError(
                f"display image: expected shape {expected} (screen height, width), got {img.shape}"
            )
        return img

    def blurred(self, image: np.ndarray) -> np.ndarray:
        """The full screen image after the optical blur (float32, dark beyond the edges)."""
        img = self._checked(image)
        if self.kernel.size == 1:
            return img
        k = self.kernel.astype(np.float32)
        return cv2.sepFilter2D(img, -1, k, k, borderType=cv2.BORDER_CONSTANT)

    def _fine(self, image: np.ndarray) -> np.ndarray:
        """Blurred image sampled at every sub-sample (H*s, W*s) float32."""
        img = self._checked(image)
        if np.array_equal(img[-1], img[0]) and np.array_equal(
            img, np.broadcast_to(img[0], img.shape)
        ):
            fx_ = self._lerp(_padded_line(_blur_line(img[0], self.kernel)), self.x0, self.fx)
            return fx_ if self._ones_y is None else fx_ * self._ones_y
        col = img[:, :1]
        if np.array_equal(img, np.broadcast_to(col, img.shape)):
            gy = self._lerp(_padded_line(_blur_line(col[:, 0], self.kernel)), self.y0, self.fy)
            return gy if self._ones_x is None else gy * self._ones_x
        return self._fine_general(self.blurred(img))

    def _fine_general(self, img: np.ndarray) -> np.ndarray:
        """Bilinear samples of an arbitrary (already blurred) image."""
        wp = self.screen.width_px + 2
        padded = cv2.copyMakeBorder(img, 1, 1, 1, 1, cv2.BORDER_REPLICATE)
        flat = np.concatenate([padded.ravel(), np.zeros(2 * wp + 2, np.float32)])
        idx = self.y0.astype(np.int64) * wp + self.x0
        top = self._lerp(flat, idx, self.fx)
        bottom = self._lerp(flat[wp:], idx, self.fx)
        return top + self.fy * (bottom - top)

    def interpolation_variance(self) -> tuple[np.ndarray, np.ndarray]:
        """Per pixel (H,W), x and y: mean of f(1-f) over sub-samples, in screen px^2.

        Linear interpolation at fraction f scales a cosine of angular frequency w by
        about exp(-f(1-f) w^2 / 2): the same loss as a Gaussian blur of variance f(1-f).
        """
        return self._pixel_mean(self.fx * (1 - self.fx)), self._pixel_mean(self.fy * (1 - self.fy))

    def _pixel_mean(self, fine: np.ndarray) -> np.ndarray:
        """Mean over each pixel's s x s sub-samples of a (H*s, W*s) array."""
        s = self.supersample
        if s == 1:
            return fine.astype(np.float32)
        total = np.zeros(self.shape, np.float32)
        for j in range(s):  # s*s strided adds: much faster than a 4-D reshape-mean
            for i in range(s):
                total += fine[j::s, i::s]
        return total * np.float32(1.0 / (s * s))

    def sample(self, image: np.ndarray) -> np.ndarray:
        """Screen image (H_s, W_s) -> (H, W) float32 mean over each pixel's sub-samples."""
        return self._pixel_mean(self._fine(image))
