"""Buffers a worker keeps between decodes (`ResidentBuffers`) and the maps file laid out in
one (`MapsFile(resident=True)`): reuse by size, the bound, and a committed file np.load reads
exactly as the mapped file's, even from a buffer that held another decode."""

from __future__ import annotations

import mmap
from pathlib import Path

import numpy as np
import pytest

from calibration.shared import maps_file
from calibration.shared.maps import DecodedMaps
from calibration.shared.maps_file import MapsFile, warm_resident
from calibration.shared.resident_buffers import ResidentBuffers
from tests.calibration.shared.npz_checks import same_npz

SHAPE = (48, 64)
AXES = ["x", "y"]
SIZE = 3 * mmap.PAGESIZE


class RecordingBuffers(ResidentBuffers):
    """Kept buffers that remember what `take` handed out, in order."""

    def __init__(self, keep: int = 4) -> None:
        super().__init__(keep=keep)
        self.taken: list[mmap.mmap] = []

    def take(self, nbytes: int) -> mmap.mmap:
        buf = super().take(nbytes)
        self.taken.append(buf)
        return buf


@pytest.fixture
def resident(monkeypatch: pytest.MonkeyPatch) -> RecordingBuffers:
    """The maps files' kept buffers, this test's own."""
    buffers = RecordingBuffers()
    monkeypatch.setattr(maps_file, "RESIDENT", buffers)
    yield buffers
    buffers.release()


def test_take_returns_a_kept_buffer_of_the_size_and_clears_other_sizes() -> None:
    kept = ResidentBuffers(keep=4)
    a = kept.take(SIZE)
    assert len(a) == SIZE
    kept.give(a)
    assert kept.kept_bytes() == SIZE
    assert kept.take(SIZE) is a
    assert kept.kept_bytes() == 0
    kept.give(a)
    b = kept.take(2 * SIZE)  # another size: `a` is dropped
    assert b is not a and len(b) == 2 * SIZE
    assert kept.kept_bytes() == 0
    assert kept.take(SIZE) is not a
    kept.release()


def test_give_keeps_at_most_keep_buffers_the_latest_and_release_drops_them() -> None:
    kept = ResidentBuffers(keep=2)
    first, second, third = (kept.take(SIZE) for _ in range(3))
    for buf in (first, second, third):
        kept.give(buf)
    assert kept.kept_bytes() == 2 * SIZE
    taken = [kept.take(SIZE), kept.take(SIZE)]
    assert {id(b) for b in taken} == {id(second), id(third)}
    assert kept.take(SIZE) is not first
    kept.give(first)
    kept.release()
    assert kept.kept_bytes() == 0
    assert kept.take(SIZE) is not first


def _commit(out: MapsFile, seed: int) -> None:
    """Decode-like outputs written into `out`'s views (as the decoder does), then commit."""
    rng = np.random.default_rng(seed)
    views = out.outputs()
    assert views is not None
    for plane in ("position", "sigma", "modulation", "blur"):
        views[plane][:] = rng.uniform(0, 100, views[plane].shape)
    views["position"][0, ::7] = np.nan
    views["mask"][:] = rng.random(views["mask"].shape) > 0.3

    def rows(plane: str) -> tuple[np.ndarray, np.ndarray]:
        return views[plane][0].reshape(SHAPE), views[plane][1].reshape(SHAPE)

    (x, y), (sx, sy), (mx, my), (bx, by) = (rows(p) for p in ("position", "sigma",
                                                             "modulation", "blur"))
    maps = DecodedMaps(x, y, sx, sy, views["mask"].reshape(SHAPE), mx, my, bx, by,
                       meta={"pose_id": f"pose_{seed}"})
    out.commit(maps, durable=False)


def test_resident_maps_file_equals_the_mapped_one_and_its_buffer_serves_the_next(
        tmp_path: Path, resident: RecordingBuffers) -> None:
    """Committed from a resident buffer, the file np.load reads equals the mapped file's;
    recycled, the buffer serves the next decode, which, though the buffer still holds the
    last decode's bytes (spoiled here), commits a file equal to the mapped one's."""
    _commit(MapsFile(tmp_path / "mapped.npz", SHAPE, AXES), seed=1)
    assert resident.taken == []
    out = MapsFile(tmp_path / "resident.npz", SHAPE, AXES, resident=True)
    [buf] = resident.taken
    _commit(out, seed=1)
    same_npz(tmp_path / "resident.npz", tmp_path / "mapped.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mapped.npz", "resident.npz"]
    assert resident.kept_bytes() == 0
    out.recycle()
    assert resident.kept_bytes() == len(buf)
    np.frombuffer(buf, np.uint8)[:] = 0xA5  # what a previous decode left, at its worst
    _commit(MapsFile(tmp_path / "mapped2.npz", SHAPE, AXES), seed=2)
    again = MapsFile(tmp_path / "resident2.npz", SHAPE, AXES, resident=True)
    assert resident.taken[-1] is buf
    _commit(again, seed=2)
    again.recycle()
    same_npz(tmp_path / "resident2.npz", tmp_path / "mapped2.npz")
    assert resident.kept_bytes() == len(buf)


def test_recycle_before_commit_or_after_close_only(tmp_path: Path,
                                                  resident: RecordingBuffers) -> None:
    """A buffer still in use is not handed out; a closed (failed) decode's is, and its
    temporary file is gone."""
    out = MapsFile(tmp_path / "maps.npz", SHAPE, AXES, resident=True)
    out.recycle()  # the decoder still writes into it
    assert resident.kept_bytes() == 0
    out.close()
    out.recycle()
    assert resident.kept_bytes() == len(resident.taken[0])
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("count", [1, 3])
def test_warm_resident_keeps_count_buffers_the_next_decodes_take(
        tmp_path: Path, resident: RecordingBuffers, count: int) -> None:
    warm_resident(SHAPE, AXES, count)
    warmed = list(resident.taken)
    size = len(warmed[0])
    assert len(warmed) == count and all(len(b) == size for b in warmed)
    assert resident.kept_bytes() == count * size
    outs = [MapsFile(tmp_path / f"maps{i}.npz", SHAPE, AXES, resident=True)
            for i in range(count)]
    assert {id(b) for b in resident.taken[count:]} == {id(b) for b in warmed}
    assert resident.kept_bytes() == 0
    for out in outs:
        out.close()
