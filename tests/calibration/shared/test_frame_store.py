"""Frame store durability: what a flush makes durable, in which order, and when."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import pytest

from calibration.shared import frame_store
from calibration.shared.frame_store import FrameStore


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


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_written_frames_read_back_exactly_with_short_writes(tmp_path: Path, dtype: type,
                                                            monkeypatch: pytest.MonkeyPatch
                                                            ) -> None:
    """Frames go in with `pwrite` (a short write continues where it stopped) and read back
    bit for bit: through np.load of the .npy stack, and through a reader's map while the
    writer still holds the file open (one page cache)."""
    real, sizes = os.pwrite, []

    def short(fd: int, data: memoryview, offset: int) -> int:
        sizes.append(len(data))
        return real(fd, data[:1000], offset)  # at most 1000 bytes per call

    monkeypatch.setattr(frame_store.os, "pwrite", short)
    rng = np.random.default_rng(3)
    frames = [(rng.random((40, 60)) * 4000).astype(dtype) for _ in range(3)]
    store = FrameStore(tmp_path, 3, flush_interval_s=0)
    for index in (2, 0):
        store.add(index, frames[index])
    reader = FrameStore(tmp_path)
    assert reader.stored().tolist() == [0, 2]
    np.testing.assert_array_equal(reader.frame(2), frames[2])
    store.add(1, frames[1][:, ::-1])  # a non-contiguous view is stored as its values
    store.close()
    np.testing.assert_array_equal(np.load(tmp_path / "frames.npy"),
                                  np.stack([frames[0], frames[1][:, ::-1], frames[2]]))
    nbytes = frames[0].nbytes
    assert sizes[:2] == [nbytes, nbytes - 1000] and len(sizes) == 3 * -(-nbytes // 1000)
