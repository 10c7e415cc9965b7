"""The capture's frame sink: copies run in a writer thread, in order, nothing is lost."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from api.pose_path import StoreSink
from calibration.decode import DecodeError
from calibration.shared.frame_store import FrameStore
from calibration.shared.progress import TaskContext


def test_frames_handed_over_are_all_stored_once_close_returns(tmp_path: Path) -> None:
    seen: list[tuple[int, int]] = []
    progress: list[int] = []
    ctx = TaskContext("job", on_progress=lambda done, total, stage: progress.append(done))
    store = FrameStore(tmp_path, 6, flush_interval_s=0)
    sink = StoreSink(store, ctx, 6, on_frame=lambda st, i: seen.append((i, int(st.frame(i)[0, 0]))))
    for i in (4, 0, 2, 5, 1, 3):
        sink.add(i, np.full((8, 9), 10 + i, np.uint8))
    sink.add(2, np.zeros((8, 9), np.uint8))  # already handed over: ignored
    sink.close()
    assert sorted(store.stored().tolist()) == list(range(6))
    assert [int(store.frame(i)[3, 3]) for i in range(6)] == [10 + i for i in range(6)]
    assert seen == [(i, 10 + i) for i in (4, 0, 2, 5, 1, 3)]  # in hand-over order
    assert progress[-1] == 6 and sink.last_stored_at is not None and sink.store_s > 0
    store.close()


def test_a_store_error_reaches_the_capture_side(tmp_path: Path) -> None:
    ctx = TaskContext("job")
    store = FrameStore(tmp_path, 3, flush_interval_s=0)
    sink = StoreSink(store, ctx, 3)
    sink.add(0, np.zeros((4, 4), np.uint8))
    sink.add(1, np.zeros((5, 4), np.uint8))  # another shape: the writer refuses it
    with pytest.raises(DecodeError, match="differs from the stored frames"):
        sink.close()
    with pytest.raises(DecodeError, match="differs from the stored frames"):
        sink.add(2, np.zeros((4, 4), np.uint8))
    assert store.stored().tolist() == [0]
    store.close()
