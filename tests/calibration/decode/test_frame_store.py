"""Frame store durability: what a flush makes durable, in which order, and when."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import pytest

from calibration.decode import frame_store
from calibration.decode.frame_store import FrameStore


@pytest.fixture
def fsyncs(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Names of the files fsynced, in order (the real fsync still runs)."""
    calls: list[str] = []
    real = os.fsync

    def spy(fd: int) -> None:
        calls.append(Path(os.readlink(f"/proc/self/fd/{fd}")).name)
        real(fd)

    monkeypatch.setattr(frame_store.os, "fsync", spy)
    return calls


def test_flush_syncs_pixels_before_markers_and_only_when_dirty(tmp_path: Path,
                                                               fsyncs: list[str]) -> None:
    store = FrameStore(tmp_path, 4, flush_interval_s=0)  # no background flusher
    store.flush()
    assert fsyncs == []  # nothing stored yet
    store.add(2, np.full((3, 5), 7, np.uint8))
    store.flush()
    assert fsyncs == ["frames.npy", "frames.done"]
    store.flush()
    assert fsyncs == ["frames.npy", "frames.done"]  # clean: nothing to do
    store.add(0, np.full((3, 5), 1, np.uint8))
    store.close()
    assert fsyncs == ["frames.npy", "frames.done"] * 2
    reread = FrameStore(tmp_path)
    assert reread.stored().tolist() == [0, 2] and int(reread.frame(2)[1, 1]) == 7


def test_background_flusher_makes_frames_durable_at_its_interval(tmp_path: Path,
                                                                 fsyncs: list[str]) -> None:
    store = FrameStore(tmp_path, 3, flush_interval_s=0.01)
    synced = threading.Event()
    real_flush = store.flush

    def flush() -> None:
        real_flush()
        if fsyncs:
            synced.set()

    store.flush = flush  # type: ignore[method-assign]
    store.add(1, np.zeros((2, 2), np.uint16))
    assert synced.wait(30), "the flusher never synced the stored frame"
    assert fsyncs[:2] == ["frames.npy", "frames.done"]
    store.close()
    assert store._flusher is None  # stopped at the end of the pose
