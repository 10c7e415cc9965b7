"""Simulated monitor: vsync on a shared clock, input latency, top-to-bottom scan-out, gamma.

`show` blocks until the next vsync and returns its time (the flip). The image reaches
the panel `latency_periods` refresh periods later; row r switches at
flip + latency*P + (r/H)*P. The display keeps a history of shown images so that
`row_weights`/`emitted` answer "what linear light did each row emit over [t0, t1]".
"""

from __future__ import annotations

import functools
import hashlib
import math
import threading
from dataclasses import dataclass

import numpy as np

from acquisition.clock import Clock
from acquisition.errors import DeviceSettingsError, DisplayError
from acquisition.protocols import DisplayInfo


@dataclass(frozen=True)
class ShownImage:
    """One image in the display history: its id (1, 2, ...; 0 = initial black) and flip time."""

    image_id: int
    flip_s: float
    codes: np.ndarray

    @functools.cached_property
    def digest(self) -> bytes:
        """A hash of the codes: the same content shown again is the same image to a camera's
        replay cache. Computed once per image, however many cameras look at it."""
        return hashlib.blake2b(np.ascontiguousarray(self.codes).tobytes(), digest_size=16).digest()


class SimulatedDisplay:
    """A `Display` with refresh rate, latency, scan-out and a power-law response."""

    def __init__(
        self,
        width_px: int,
        height_px: int,
        clock: Clock,
        *,
        refresh_hz: float = 60.0,
        latency_periods: int = 2,
        gamma: float = 2.2,
        bit_depth: int = 8,
        vsync_phase_s: float = 0.0,
        history_s: float = 10.0,
        name: str = "simulated display",
    ) -> None:
        if width_px <= 0 or height_px <= 0:
            raise DeviceSettingsError(
                f"display size: expected positive, got {width_px}x{height_px}")
        if not 1.0 <= refresh_hz <= 1000.0:
            raise DeviceSettingsError(f"refresh_hz: expected 1..1000 Hz, got {refresh_hz}")
        if latency_periods < 0:
            raise DeviceSettingsError(f"latency_periods: expected >= 0, got {latency_periods}")
        if bit_depth not in (8, 10):
            raise DeviceSettingsError(f"display bit_depth: expected 8 or 10, got {bit_depth}")
        if gamma <= 0:
            raise DeviceSettingsError(f"gamma: expected > 0, got {gamma}")
        self._info = DisplayInfo(name, width_px, height_px, refresh_hz, bit_depth)
        self.clock = clock
        self.latency_periods = int(latency_periods)
        self.vsync_phase_s = float(vsync_phase_s)
        self.history_s = float(history_s)
        top = (1 << bit_depth) - 1
        self.gamma = float(gamma)
        self.lut = ((np.arange(top + 1) / top) ** gamma).astype(np.float32)
        self.brightness = 1.0  # relative panel luminance (drift injection)
        self._dtype = np.uint8 if bit_depth == 8 else np.uint16
        black = np.zeros((height_px, width_px), self._dtype)
        self._history: list[ShownImage] = [ShownImage(0, -math.inf, black)]
        self._lock = threading.Lock()
        self._closed = False

    @property
    def info(self) -> DisplayInfo:
        """Size, refresh rate and code depth."""
        return self._info

    @property
    def period_s(self) -> float:
        """One refresh period in seconds."""
        return 1.0 / self._info.refresh_hz

    @property
    def latency_s(self) -> float:
        """True flip-to-panel delay (ground truth; the controller measures it)."""
        return self.latency_periods * self.period_s

    def next_vsync(self, t: float) -> float:
        """First vsync strictly after time `t`."""
        p = self.period_s
        k = math.floor((t - self.vsync_phase_s) / p) + 1
        return self.vsync_phase_s + k * p

    def show(self, image: np.ndarray) -> float:
        """Queue `image` (device codes) for the next vsync, wait for it, return the flip time."""
        if self._closed:
            raise DisplayError(f"{self._info.name}: show() after close()")
        img = np.asarray(image)
        shape = (self._info.height_px, self._info.width_px)
        if img.shape != shape or img.dtype != self._dtype:
            raise DisplayError(f"{self._info.name}: expected a {shape} {np.dtype(self._dtype)} "
                               f"image, got {img.shape} {img.dtype}")
        flip = self.next_vsync(self.clock.now())
        self.clock.sleep_until(flip)
        with self._lock:
            last = self._history[-1]
            if flip <= last.flip_s:
                raise DisplayError(f"{self._info.name}: two images for the vsync at {flip:.6f} s")
            self._history.append(ShownImage(last.image_id + 1, flip, img.copy()))
            self._prune(flip)
        return flip

    def _prune(self, now: float) -> None:
        """Forget images fully replaced on the panel more than `history_s` ago."""
        horizon = now - self.history_s
        while len(self._history) > 2 and self._row_start(self._history[2].flip_s, 1.0) < horizon:
            self._history.pop(0)

    def _row_start(self, flip: float, row_frac: np.ndarray | float) -> np.ndarray | float:
        """Time at which the image flipped at `flip` reaches row fraction r/H."""
        return flip + (self.latency_periods + row_frac) * self.period_s

    def history(self) -> list[ShownImage]:
        """Images still remembered, oldest first."""
        with self._lock:
            return list(self._history)

    def row_weights(self, t0: float, t1: float) -> tuple[list[ShownImage], np.ndarray]:
        """Images on the panel during [t0, t1] and their time weights per row, shape (n, H).

        Weights of a row sum to 1; an image absent from the window is left out.
        """
        if not t1 > t0:
            raise ValueError(f"row_weights: empty window [{t0}, {t1}]")
        with self._lock:
            hist = list(self._history)
        if self._row_start(hist[0].flip_s, 0.0) > t0 and hist[0].image_id != 0:
            raise DisplayError(f"{self._info.name}: window starting at {t0:.6f} s is older "
                               f"than the kept history ({self.history_s} s)")
        # only images on some row during [t0, t1] (plus the next, which ends the last):
        # image k covers [start of its first row, start of image k+1's last row)
        first = 0
        while first + 1 < len(hist) and self._row_start(hist[first + 1].flip_s, 1.0) <= t0:
            first += 1
        stop = first + 1
        while stop < len(hist) and self._row_start(hist[stop].flip_s, 0.0) < t1:
            stop += 1
        hist = hist[first:stop + 1]
        frac = np.arange(self._info.height_px) / self._info.height_px
        starts = np.stack([np.broadcast_to(self._row_start(h.flip_s, frac), frac.shape)
                           for h in hist])
        ends = np.vstack([starts[1:], np.full((1, frac.size), np.inf)])
        overlap = np.clip(np.minimum(ends, t1) - np.maximum(starts, t0), 0.0, None)
        weights = overlap / (t1 - t0)
        keep = weights.max(axis=1) > 0
        return [h for h, k in zip(hist, keep, strict=True) if k], weights[keep]

    def emitted(self, t0: float, t1: float) -> np.ndarray:
        """Mean linear light (H, W) float32 in [0, 1] each screen pixel emitted over [t0, t1]."""
        shown, weights = self.row_weights(t0, t1)
        out = np.zeros((self._info.height_px, self._info.width_px), np.float32)
        for img, w in zip(shown, weights, strict=True):
            out += self.lut[img.codes] * w[:, None].astype(np.float32)
        return out * np.float32(self.brightness)

    def close(self) -> None:
        """Release the display (further `show` calls fail)."""
        self._closed = True
