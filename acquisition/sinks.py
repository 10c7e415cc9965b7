"""Where the controller hands accepted frames: the streaming decoder or a store."""

from __future__ import annotations

from typing import Protocol

import numpy as np


class FrameSink(Protocol):
    """Receives each accepted frame exactly once, tagged with its plan frame index.

    `calibration.decode.StreamingDecoder` implements this; so does `MemoryFrameStore`.
    """

    def add(self, index: int, image: np.ndarray) -> None: ...


class MemoryFrameStore:
    """Keeps accepted frames in memory by plan index (tests, export to `.npy`)."""

    def __init__(self) -> None:
        self.frames: dict[int, np.ndarray] = {}

    def add(self, index: int, image: np.ndarray) -> None:
        if index in self.frames:
            raise ValueError(f"frame {index} was already stored (duplicate hand-off)")
        self.frames[index] = image

    def stack(self, count: int) -> np.ndarray:
        """All frames 0..count-1 as one (F, H, W) array; raises if any is missing."""
        missing = [i for i in range(count) if i not in self.frames]
        if missing:
            raise ValueError(f"missing frames {missing[:10]} (of {len(missing)})")
        return np.stack([self.frames[i] for i in range(count)])
