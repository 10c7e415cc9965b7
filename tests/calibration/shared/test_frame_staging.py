"""Frames staged in shared memory for the live decode (`frame_staging`, `FrameStore(stage=True)`):
the file on disk stays a plain .npy, a reader takes staged frames from the buffer and the rest
from the file, a buffer serves another pose only once its reader is done, a reader behind a
reused buffer fails rather than reading another pose's pixels, O_DIRECT falls back to buffered
writes, and buffers left by dead processes are removed."""

from __future__ import annotations

import errno
import os
import resource
import subprocess
from pathlib import Path

import numpy as np
import pytest

from calibration.decode.accumulate import DecodeError
from calibration.shared import frame_staging, frame_store
from calibration.shared.frame_staging import (
    HEADER_BYTES,
    MAX_FRAMES,
    SIDECAR,
    StagedFrames,
    StagingBuffer,
    StagingPool,
    write_sidecar,
)
from calibration.shared.frame_store import FrameStore

COUNT = 6
SHAPE = (16, 32)  # uint16: 1024 bytes a frame, a multiple of 512 (O_DIRECT)
REAL_OPEN, REAL_CLOSE, REAL_PWRITE = os.open, os.close, os.pwrite


def _frames(dtype: type = np.uint16, shape: tuple[int, int] = SHAPE,
            seed: int = 5) -> np.ndarray:
    """A stack of distinct frames (no two equal, none zero)."""
    rng = np.random.default_rng(seed)
    return rng.integers(1, 250, size=(COUNT, *shape)).astype(dtype)


def _store_all(folder: Path, frames: np.ndarray, order: list[int] | None = None) -> None:
    """A staged store of `frames` (those in `order`, in that order), closed: a capture."""
    store = FrameStore(folder, COUNT, stage=True, flush_interval_s=0)
    for i in order if order is not None else range(COUNT):
        store.add(i, frames[i])
    store.close()


class RecordingPool(StagingPool):
    """A pool in the test's folder that remembers the buffers it leased, in order."""

    def __init__(self, folder: Path, limit_bytes: int) -> None:
        super().__init__(folder, limit_bytes)
        self.leased: list[StagingBuffer] = []

    def lease(self, count: int, nbytes: int) -> StagingBuffer | None:
        buf = super().lease(count, nbytes)
        if buf is not None:
            self.leased.append(buf)
        return buf


@pytest.fixture
def pool(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> RecordingPool:
    """The frame stores' pool, in the test's folder instead of /dev/shm; nothing left after."""
    folder = tmp_path / "shm"
    folder.mkdir()
    recording = RecordingPool(folder, 1 << 20)
    monkeypatch.setattr(frame_store, "POOL", recording)
    yield recording
    recording.close()
    assert list(folder.iterdir()) == []


# -- 1. the file on disk ------------------------------------------------------------------

@pytest.mark.parametrize(("dtype", "shape"), [(np.uint16, SHAPE), (np.uint8, (10, 10))])
def test_staged_store_writes_a_npy_with_its_pixels_at_4096(tmp_path: Path, pool: RecordingPool,
                                                           dtype: type,
                                                           shape: tuple[int, int]) -> None:
    """Written out of order, through O_DIRECT (1024-byte frames) or not (100 bytes), the
    file is a .npy np.load reads exactly, its header padded so the pixels start at 4096."""
    frames = _frames(dtype, shape)
    folder = tmp_path / "pose"
    _store_all(folder, frames, order=[3, 0, 5, 1, 4, 2])
    assert len(pool.leased) == 1  # staged
    path = folder / "frames.npy"
    got = np.load(path, allow_pickle=False)
    assert got.dtype == frames.dtype and got.shape == frames.shape
    np.testing.assert_array_equal(got, frames)
    with open(path, "rb") as fh:
        assert np.lib.format.read_magic(fh) == (1, 0)
        np.lib.format.read_array_header_1_0(fh)
        assert fh.tell() == 4096
    assert path.stat().st_size == 4096 + frames.nbytes
    reader = FrameStore(folder)  # as `phasecal decode` opens a stored pose
    np.testing.assert_array_equal(reader.array(), frames)
    assert reader.stored().tolist() == list(range(COUNT))


# -- 2. a reader in the same process ------------------------------------------------------

def test_reader_takes_staged_frames_from_the_buffer_and_earlier_ones_from_the_file(
        tmp_path: Path, pool: RecordingPool) -> None:
    """A capture resumed with staging: frames stored before come from the file, the staged
    ones from shared memory (their copy on disk spoiled here, so a read from the file would
    show); the sidecar stays past the writer's close until the reader is done."""
    frames = _frames()
    folder = tmp_path / "pose"
    first = FrameStore(folder, COUNT, flush_interval_s=0)  # interrupted, not staged
    for i in (0, 1):
        first.add(i, frames[i])
    first.close()
    assert not (folder / SIDECAR).exists()
    _store_all(folder, frames, order=list(range(2, COUNT)))
    [buf] = pool.leased
    with open(folder / "frames.npy", "r+b") as fh:  # spoil frame 3's copy on disk
        fh.seek(4096 + 3 * frames[0].nbytes)
        fh.write(bytes(frames[0].nbytes))
    reader = FrameStore(folder, COUNT)
    groups = reader.sources(list(range(COUNT)))
    assert [part for part, _ in groups] == [[2, 3, 4, 5], [0, 1]]
    (staged, shm), (unstaged, disk) = groups
    assert disk is reader.array() and shm is not disk
    np.testing.assert_array_equal(shm[staged], frames[2:])
    np.testing.assert_array_equal(disk[unstaged], frames[:2])
    assert not disk[3].any()  # (the spoiled copy: what the buffer's slot replaced)
    reader.verify()
    assert not shm.flags.writeable
    assert (folder / SIDECAR).exists()  # the writer closed, the reader not yet done
    assert not buf.reader_done()
    reader.reader_done()
    assert buf.reader_done()
    assert not (folder / SIDECAR).exists()


def test_reader_done_before_the_writer_closes_reads_the_file_from_then_on(
        tmp_path: Path, pool: RecordingPool) -> None:
    frames = _frames()
    folder = tmp_path / "pose"
    store = FrameStore(folder, COUNT, stage=True, flush_interval_s=0)
    for i in range(COUNT):
        store.add(i, frames[i])
    reader = FrameStore(folder, COUNT)
    [(part, shm)] = reader.sources(list(range(COUNT)))
    np.testing.assert_array_equal(shm[part], frames)
    reader.reader_done()
    store.close()
    assert not (folder / SIDECAR).exists()
    assert reader.sources([0])[0][1] is reader.array()  # done: the file from now on


# -- 3. the pool --------------------------------------------------------------------------

def _reader_done(folder: Path, buf: StagingBuffer) -> None:
    """Name `buf` to a reader of `folder`, which reads nothing and says it is done."""
    folder.mkdir(exist_ok=True)
    write_sidecar(folder, buf, SHAPE, np.dtype(np.uint16))
    reader = StagedFrames.attach(folder, buf.count)
    assert reader is not None
    reader.done()
    reader.close()


def test_pool_reuses_a_buffer_only_when_given_back_and_its_reader_is_done(
        tmp_path: Path) -> None:
    pool = StagingPool(tmp_path, limit_bytes=1 << 20)
    try:
        a = pool.lease(4, 1024)
        assert a is not None
        token = a.token
        _reader_done(tmp_path / "a", a)
        b = pool.lease(4, 1024)  # `a` still leased, though its reader is done
        assert b is not None and b is not a
        pool.give_back(b)  # given back, its reader not done
        c = pool.lease(4, 1024)
        assert c is not None and c not in (a, b)
        pool.give_back(a)
        assert pool.lease(4, 1024) is a
        assert a.token != token and not a.reader_done()  # a new pose in it
        pool.give_back(a)
        _reader_done(tmp_path / "a2", a)
        assert pool.lease(4, 2048) not in (None, a)  # another frame size
        assert pool.lease(5, 1024) not in (None, a)  # another frame count
        assert pool.lease(4, 1024) is a
    finally:
        pool.close()
    assert not list(tmp_path.glob("phasecal-frames-*"))


def test_pool_reuses_a_buffer_whose_reader_never_said_so_after_reuse_after_s(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pool = StagingPool(tmp_path, limit_bytes=1 << 20)
    try:
        a = pool.lease(4, 1024)
        pool.give_back(a)
        assert pool.lease(4, 1024) is not a  # 60 s have not passed
        monkeypatch.setattr(frame_staging, "REUSE_AFTER_S", 0.0)
        assert pool.lease(4, 1024) is a
    finally:
        pool.close()


def test_pool_leases_nothing_past_its_limit_without_a_folder_or_over_max_frames(
        tmp_path: Path) -> None:
    one = HEADER_BYTES + 4 * 1024
    pool = StagingPool(tmp_path, limit_bytes=one)
    try:
        a = pool.lease(4, 1024)
        assert a is not None
        pool.give_back(a)
        assert pool.lease(4, 1024) is None  # `a` not reusable, no room for another
        assert pool.lease(1, 16) is None
        _reader_done(tmp_path / "a", a)
        assert pool.lease(4, 1024) is a  # reuse needs no room
        assert pool.lease(1, 16) is None  # `a` leased: not freed for another size
        pool.give_back(a)
        _reader_done(tmp_path / "a2", a)
        b = pool.lease(2, 1024)  # `a`, reusable, freed to make room for another size
        assert b is not None and b is not a
        assert not a.path.exists() and b.path.exists()
    finally:
        pool.close()
    assert StagingPool(tmp_path / "missing").lease(4, 1024) is None
    big = StagingPool(tmp_path, limit_bytes=1 << 20)
    try:
        assert big.lease(MAX_FRAMES + 1, 16) is None
        edge = big.lease(MAX_FRAMES, 16)  # the last frame's "staged" byte ends the header
        assert edge is not None
        slots = edge.frames((2, 4), np.dtype(np.uint16))
        edge.put(MAX_FRAMES - 1, np.full((2, 4), 7, np.uint16), slots)
        assert edge.holds(MAX_FRAMES - 1) and not edge.holds(MAX_FRAMES - 2)
        assert edge.token == bytes(edge.header[:16]).hex()  # the token not overwritten
    finally:
        big.close()


# -- 4. a reader behind a reused buffer ---------------------------------------------------

def test_reader_of_a_reused_buffer_fails_and_a_stale_sidecar_is_not_attached(
        tmp_path: Path, pool: RecordingPool, monkeypatch: pytest.MonkeyPatch) -> None:
    """Pose A's buffer leased again for pose B under A's reader (its reader never said it
    was done): the reader's check fails with the reason, and its next read takes the file;
    a new reader of A reads the file;
    A's stale reader does not mark B's buffer done."""
    monkeypatch.setattr(frame_staging, "REUSE_AFTER_S", 0.0)
    frames = _frames()
    _store_all(tmp_path / "a", frames)
    reader = FrameStore(tmp_path / "a", COUNT)
    [(part, shm)] = reader.sources(list(range(COUNT)))
    np.testing.assert_array_equal(shm[part], frames)
    reader.verify()
    other = FrameStore(tmp_path / "b", COUNT, stage=True, flush_interval_s=0)
    other.add(0, frames[0][::-1].copy())  # pose B's first frame, in A's slot 0
    assert pool.leased[1] is pool.leased[0]
    with pytest.raises(DecodeError, match="reused by another capture"):
        reader.verify()
    # the reader's next read, after the reuse, takes this pose's frames from the file
    [(part, disk)] = reader.sources(list(range(COUNT)))
    assert disk is reader.array()
    np.testing.assert_array_equal(disk[part], frames)
    reader.verify()
    assert StagedFrames.attach(tmp_path / "a", COUNT) is None
    late = FrameStore(tmp_path / "a", COUNT)
    [(part, disk)] = late.sources(list(range(COUNT)))
    assert disk is late.array()
    np.testing.assert_array_equal(disk[part], frames)
    reader.reader_done()
    assert not pool.leased[1].reader_done()
    other.close()


def test_staged_frames_check_sees_the_token_change(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(frame_staging, "REUSE_AFTER_S", 0.0)
    pool = StagingPool(tmp_path / "shm", limit_bytes=1 << 20)
    (tmp_path / "shm").mkdir()
    try:
        buf = pool.lease(3, 1024)
        write_sidecar(tmp_path, buf, SHAPE, np.dtype(np.uint16))
        assert StagedFrames.attach(tmp_path, 4) is None  # another plan's count
        reader = StagedFrames.attach(tmp_path, 3)
        assert reader is not None
        slots = buf.frames(SHAPE, np.dtype(np.uint16))
        buf.put(1, np.full(SHAPE, 9, np.uint16), slots)
        assert reader.staged([0, 1, 2]) == [1]
        assert (reader.frames[1] == 9).all()
        reader.check()
        pool.give_back(buf)
        assert pool.lease(3, 1024) is buf
        assert reader.staged([0, 1, 2]) == []  # the new pose staged nothing yet
        with pytest.raises(DecodeError):
            reader.check()
        reader.close()
    finally:
        pool.close()


# -- 5. O_DIRECT and its fallback ---------------------------------------------------------

class DirectIO:
    """Stands in for the filesystem's O_DIRECT: descriptors frame_store opens with it are
    opened buffered and remembered until closed (so the test does not depend on the disk
    under tmp_path), and the first `fail` writes to them raise OSError(`errno_`)."""

    def __init__(self, fail: int = 0, errno_: int = errno.EINVAL) -> None:
        self.fail, self.errno = fail, errno_
        self.opened = 0
        self.writes = 0
        self.fds: set[int] = set()

    def open(self, path: str | Path, flags: int, *args: int) -> int:
        if not flags & os.O_DIRECT:
            return REAL_OPEN(path, flags, *args)
        self.opened += 1
        fd = REAL_OPEN(path, flags & ~os.O_DIRECT, *args)
        self.fds.add(fd)
        return fd

    def close(self, fd: int) -> None:
        self.fds.discard(fd)  # (its number may come back for a buffered descriptor)
        REAL_CLOSE(fd)

    def pwrite(self, fd: int, data: memoryview, offset: int) -> int:
        if fd in self.fds:
            self.writes += 1
            if self.fail:
                self.fail -= 1
                raise OSError(self.errno, os.strerror(self.errno))
            address = np.frombuffer(data, np.uint8).ctypes.data  # what O_DIRECT needs:
            assert offset % 512 == 0 and len(data) % 512 == 0 and address % 512 == 0
        return REAL_PWRITE(fd, data, offset)


def _direct_io(monkeypatch: pytest.MonkeyPatch, **kwargs: int) -> DirectIO:
    direct = DirectIO(**kwargs)
    monkeypatch.setattr(frame_store.os, "open", direct.open)
    monkeypatch.setattr(frame_store.os, "close", direct.close)
    monkeypatch.setattr(frame_store.os, "pwrite", direct.pwrite)
    return direct


@pytest.mark.parametrize(("dtype", "shape", "direct"),
                         [(np.uint16, SHAPE, True), (np.float32, (8, 32), True),
                          (np.uint8, (10, 10), False), (np.uint16, (10, 30), False)])
def test_o_direct_only_for_frames_a_multiple_of_512_bytes(
        tmp_path: Path, pool: RecordingPool, monkeypatch: pytest.MonkeyPatch, dtype: type,
        shape: tuple[int, int], direct: bool) -> None:
    io = _direct_io(monkeypatch)
    frames = _frames(dtype, shape)
    _store_all(tmp_path / "pose", frames)
    assert (io.opened, io.writes) == ((1, COUNT) if direct else (0, 0))
    np.testing.assert_array_equal(np.load(tmp_path / "pose" / "frames.npy"), frames)


def test_first_o_direct_write_refused_falls_back_to_buffered_writes(
        tmp_path: Path, pool: RecordingPool, monkeypatch: pytest.MonkeyPatch) -> None:
    io = _direct_io(monkeypatch, fail=1)
    frames = _frames()
    _store_all(tmp_path / "pose", frames, order=[2, 0, 1, 3, 4, 5])
    assert (io.opened, io.writes) == (1, 1)  # refused once, closed, buffered from then on
    assert not io.fds
    np.testing.assert_array_equal(np.load(tmp_path / "pose" / "frames.npy"), frames)
    reader = FrameStore(tmp_path / "pose", COUNT)
    [(part, shm)] = reader.sources(list(range(COUNT)))  # staged all the same
    np.testing.assert_array_equal(shm[part], frames)
    reader.reader_done()


def test_o_direct_write_error_other_than_einval_is_raised(
        tmp_path: Path, pool: RecordingPool, monkeypatch: pytest.MonkeyPatch) -> None:
    _direct_io(monkeypatch, fail=1, errno_=errno.EIO)
    store = FrameStore(tmp_path / "pose", COUNT, stage=True, flush_interval_s=0)
    with pytest.raises(OSError) as caught:
        store.add(0, _frames()[0])
    assert caught.value.errno == errno.EIO
    store.close()


def test_store_resumed_with_an_unpadded_header_never_opens_o_direct(
        tmp_path: Path, pool: RecordingPool, monkeypatch: pytest.MonkeyPatch) -> None:
    """A store made by np.save (pixels at 128, not on a disk block) resumed with staging:
    staged, written buffered."""
    frames = _frames()
    folder = tmp_path / "pose"
    folder.mkdir()
    np.save(folder / "frames.npy", np.zeros_like(frames))
    (folder / "frames.done").write_bytes(bytes(COUNT))
    io = _direct_io(monkeypatch)
    _store_all(folder, frames)
    assert len(pool.leased) == 1 and io.opened == 0
    np.testing.assert_array_equal(np.load(folder / "frames.npy"), frames)


# -- 6. buffers of processes that ended ---------------------------------------------------

def test_first_lease_removes_buffers_of_dead_processes_only(tmp_path: Path) -> None:
    ended = subprocess.Popen(["true"])
    ended.wait()
    dead = tmp_path / f"phasecal-frames-{ended.pid}-1"
    alive = tmp_path / f"phasecal-frames-{os.getppid()}-3"
    unrelated = tmp_path / f"other-{ended.pid}-1"
    for path in (dead, alive, unrelated):
        path.write_bytes(b"x")
    pool = StagingPool(tmp_path, limit_bytes=1 << 20)
    try:
        assert pool.lease(2, 512) is not None
        assert not dead.exists()
        assert alive.exists() and unrelated.exists()
    finally:
        pool.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([alive.name, unrelated.name])


# -- 7. a reader's mappings, kept from pose to pose ---------------------------------------

def _read_all(frames: np.ndarray) -> int:
    """Page faults of this thread while every byte of `frames` is read once."""
    before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
    int(frames.sum(dtype=np.uint64))
    return resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before


def test_reader_reads_a_reused_buffer_through_its_kept_mapping(
        tmp_path: Path, pool: RecordingPool, monkeypatch: pytest.MonkeyPatch) -> None:
    """Pose after pose, a camera's frames come through the same buffer: the decode worker
    maps it once (a buffer mapped afresh each pose faulted its page tables in again: ~4000
    faults per 250 MB), and reads each pose's pixels from it."""
    kept = frame_staging.ReaderMappings()
    monkeypatch.setattr(frame_staging, "READER_MAPS", kept)
    faults = []
    for pose, seed in enumerate((5, 6)):
        frames = _frames(shape=(128, 512), seed=seed)  # 128 KiB a frame
        folder = tmp_path / f"pose{pose}"
        _store_all(folder, frames)
        reader = FrameStore(folder, COUNT)
        [(part, shm)] = reader.sources(list(range(COUNT)))
        faults.append(_read_all(shm))
        np.testing.assert_array_equal(shm[part], frames)
        reader.verify()
        reader.reader_done()
        del shm
    assert len(pool.leased) == 2 and pool.leased[0] is pool.leased[1]  # one buffer, reused
    assert len(kept) == 1
    assert faults[0] >= 10 and 4 * faults[1] <= faults[0], faults


def test_kept_mappings_follow_their_files(tmp_path: Path) -> None:
    """A removed or replaced buffer's mapping is closed at the next `get` (its memory is held
    while mapped); at most `keep` are kept, the least recently used dropped first."""
    kept = frame_staging.ReaderMappings(keep=2)
    paths = []
    for k in range(3):
        path = tmp_path / f"buf{k}"
        path.write_bytes(bytes([k + 1]) * 8192)
        paths.append(str(path))
    try:
        a = kept.get(paths[0])
        assert kept.get(paths[0]) is a and a[0] == 1
        b = kept.get(paths[1])
        os.unlink(paths[0])
        assert kept.get(paths[1]) is b and len(kept) == 1 and a.closed
        Path(paths[1]).unlink()  # replaced: another file at the same path
        Path(paths[1]).write_bytes(bytes([9]) * 8192)
        b2 = kept.get(paths[1])
        assert b2 is not b and b.closed and b2[0] == 9
        c = kept.get(paths[2])
        Path(paths[0]).write_bytes(bytes([7]) * 8192)
        kept.get(paths[0])  # a third: the least recently used (paths[1]) goes
        assert len(kept) == 2 and b2.closed and not c.closed
        with pytest.raises(OSError):
            kept.get(str(tmp_path / "missing"))
    finally:
        kept.release()
    assert len(kept) == 0 and c.closed
