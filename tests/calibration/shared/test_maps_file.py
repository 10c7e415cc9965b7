"""The maps file laid out before the decode (`MapsFile`): the decoder writes into its pages,
the result is an NPZ np.load reads with the same arrays as the normal path's, and nothing is
left at the destination when the decode fails, is cancelled, is killed or the disk is full."""

from __future__ import annotations

import errno
import os
import struct
import subprocess
import sys
import textwrap
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

import calibration.decode.decoder as decoder_module
from acquisition.patterns import build_plan
from api.worker import tasks
from api.worker.tasks import stream_decode_task
from calibration import prefault
from calibration.decode import DecodeError, StreamingDecoder
from calibration.decode.options import DecodeOptions
from calibration.prefault import IdlePrefault, populate
from calibration.shared.frame_store import FrameStore
from calibration.shared.maps import save_maps
from calibration.shared.maps_file import MapsFile
from calibration.shared.plan import write_plan
from calibration.shared.progress import Cancelled, TaskContext
from calibration.shared.resident_buffers import RESIDENT
from tests.calibration.decode.test_decode import H, W, render
from tests.calibration.shared.npz_checks import same_npz

ROOT = Path(__file__).resolve().parents[3]
META = {"pose_id": "pose_1"}


@pytest.fixture(scope="module")
def plan():
    return build_plan(1920, 1080, 0.2745)


@pytest.fixture(scope="module")
def stack(plan):
    frames, _, _ = render(plan, white=320.0, blur=1.5, seed=37)  # clipped samples, blur
    frames[:, :, :6] = 0  # a black border: every step clipped
    return frames


def _decoder(plan, stack, options=None):
    dec = StreamingDecoder(plan, (H, W), options=options)
    dec.prepare()
    dec.add_frames(list(range(stack.shape[0])), stack)
    return dec


def _mapped(path: Path) -> bool:
    """True while this process maps the file at `path` (its inode in /proc/self/maps)."""
    ino = str(os.stat(path).st_ino)
    with open("/proc/self/maps") as maps:
        return any(len(f) > 4 and f[4] == ino for f in (line.split() for line in maps))


def _data_offsets(path: Path) -> dict[str, int]:
    """Each member's array data offset, read from its local header and .npy header."""
    raw = path.read_bytes()
    out = {}
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            at = info.header_offset
            name_len, extra_len = struct.unpack("<HH", raw[at + 26:at + 30])
            npy = at + 30 + name_len + extra_len
            header_len = struct.unpack("<H", raw[npy + 8:npy + 10])[0]
            out[info.filename] = npy + 10 + header_len
    return out


@pytest.mark.parametrize("compiled", [False, True])
def test_decoder_writes_into_the_file_with_the_normal_paths_arrays(plan, stack, compiled,
                                                                   tmp_path, monkeypatch):
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0 if compiled else 1 << 40)
    save_maps(_decoder(plan, stack).finish(dict(META)), tmp_path / "ref.npz")
    with MapsFile(tmp_path / "maps.npz", (H, W), plan.axes()) as out:
        populate(out.mapped, 0, out.mapped.nbytes)
        maps = _decoder(plan, stack).finish(dict(META), into=out.outputs())
        out.commit(maps)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["maps.npz", "ref.npz"]
    same_npz(tmp_path / "maps.npz", tmp_path / "ref.npz")
    # the decoder's arrays were the file's pages (no copy): read-only now
    for key in ("x", "y", "sigma_x", "sigma_y", "mask", "modulation_x", "blur_y"):
        assert not getattr(maps, key).flags.writeable, key
    offsets = _data_offsets(tmp_path / "maps.npz")
    assert all(offsets[f"{k}.npy"] % 4096 == 0 for k in ("x", "y", "mask", "blur_y"))


def test_maps_not_decoded_into_the_file_are_copied_in(plan, stack, tmp_path, monkeypatch,
                                                      normal_priority):
    """Arrays from elsewhere (a decoder given no outputs) are copied; the pages are touched
    one by one where madvise cannot (no libc, an older kernel)."""
    monkeypatch.setattr(prefault, "_libc_madvise", lambda: None)
    maps = _decoder(plan, stack).finish(dict(META))
    save_maps(maps, tmp_path / "ref.npz")
    with MapsFile(tmp_path / "maps.npz", (H, W), plan.axes()) as out:
        with IdlePrefault([out.mapped], piece=3 << 12) as ahead:
            _wait_for(ahead)
        out.commit(maps)
    same_npz(tmp_path / "maps.npz", tmp_path / "ref.npz")
    assert maps.x.flags.writeable  # the caller's own arrays are untouched


def test_wrong_members_are_refused_and_nothing_is_left(plan, stack, tmp_path):
    maps = _decoder(plan, stack).finish(dict(META))
    maps.blur_y = None
    with pytest.raises(ValueError, match="differ from the laid-out"):
        with MapsFile(tmp_path / "maps.npz", (H, W), plan.axes()) as out:
            out.commit(maps)
    assert list(tmp_path.iterdir()) == []


def test_failed_decode_leaves_nothing(plan, tmp_path):
    dark = np.zeros((len(plan.frames), H, W), np.uint8)
    with pytest.raises(DecodeError, match="no pixel sees the screen"):
        with MapsFile(tmp_path / "maps.npz", (H, W), plan.axes()) as out:
            populate(out.mapped, 0, 1 << 20)
            _decoder(plan, dark).finish(into=out.outputs())
    assert list(tmp_path.iterdir()) == []


def test_full_disk_is_a_clear_error_before_any_decoding(plan, tmp_path, monkeypatch):
    def full(fd, offset, length):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full)
    with pytest.raises(OSError, match=r"cannot reserve 2 MB for the maps \(No space left"):
        MapsFile(tmp_path / "maps.npz", (H, W), plan.axes())
    assert list(tmp_path.iterdir()) == []


@pytest.fixture
def normal_priority(monkeypatch):
    """The prefault thread at normal priority: at idle priority it may starve on a loaded
    machine, and a test must not depend on the load."""
    monkeypatch.delattr(os, "SCHED_IDLE")


def _wait_for(ahead: IdlePrefault) -> None:
    for _ in range(6000):
        if ahead.done == ahead.total:
            return
        threading.Event().wait(0.005)


@pytest.mark.parametrize("madvise", [True, False])
def test_background_prefault_covers_the_regions_and_reports_its_error(plan, tmp_path,
                                                                      monkeypatch, madvise,
                                                                      normal_priority):
    if not madvise:  # each page touched instead (no libc, a kernel before 5.14)
        monkeypatch.setattr(prefault, "_libc_madvise", lambda: None)
    other = tmp_path / "other.bin"
    other.write_bytes(b"")
    os.truncate(other, 3 << 20)  # sparse, not yet written
    region = np.memmap(other, mode="r+", dtype=np.uint8)
    with MapsFile(tmp_path / "maps.npz", (H, W), plan.axes()) as out:
        with IdlePrefault([region, out.mapped], piece=1 << 14) as ahead:
            _wait_for(ahead)
        assert ahead.done == ahead.total == (3 << 20) + out.mapped.nbytes
        assert not any(t.name == "prefault" for t in threading.enumerate())
        assert not region.any()  # contents unchanged
    del region

    def fails(view, start, length):
        raise OSError(14, "cannot fault in mapped pages (Bad address)")

    monkeypatch.setattr(prefault, "populate", fails)
    with MapsFile(tmp_path / "maps.npz", (H, W), plan.axes()) as out:
        ahead = IdlePrefault([out.mapped]).start()
        with pytest.raises(OSError, match="cannot fault in"):
            ahead.stop()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.bin"]


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="no SCHED_IDLE on this OS")
def test_prefault_thread_runs_at_idle_priority_until_stopped(plan, tmp_path, monkeypatch):
    policies: list[tuple[bool, int]] = []
    real = os.sched_setscheduler

    def recorded(pid, policy, param):
        policies.append((pid == 0, policy))
        return real(pid, policy, param)

    monkeypatch.setattr(os, "sched_setscheduler", recorded)
    with MapsFile(tmp_path / "maps.npz", (H, W), plan.axes()) as out:
        ahead = IdlePrefault([out.mapped]).start()
        for _ in range(6000):  # until the thread has set its own priority
            if policies:
                break
            threading.Event().wait(0.005)
        ahead.stop()
    assert policies[0] == (True, os.SCHED_IDLE)  # the thread itself
    assert all(policy == os.SCHED_OTHER for _, policy in policies[1:])  # raised by stop


def test_killed_writer_leaves_no_maps_at_the_destination(tmp_path):
    script = textwrap.dedent(f"""
        import time
        from calibration.shared.maps_file import MapsFile
        from calibration.prefault import populate
        out = MapsFile({str(tmp_path / "maps.npz")!r}, (64, 80), ["x", "y"])
        populate(out.mapped, 0, out.mapped.nbytes)
        print("laid out", flush=True)
        time.sleep(30)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().startswith("laid out")
    finally:
        proc.kill()
        proc.wait()
    leftovers = [p.name for p in tmp_path.iterdir()]
    assert len(leftovers) == 1 and leftovers[0].startswith(".maps.")  # the job's staging
    # folder, which holds it, is removed by the server (api/store.py `staging`)


def _x_on_disk(out: MapsFile, rows: int) -> np.ndarray:
    """The leading `rows` rows of member x as the file on disk holds them now (the resident
    buffer's blocks go with O_DIRECT, past the page cache)."""
    (tmp,) = [p for p in out.path.parent.iterdir() if p.name.startswith(f".{out.path.stem}.")]
    offset = out.outputs()["position"][0].ctypes.data - out.mapped.ctypes.data
    with open(tmp, "rb", buffering=0) as f:
        return np.frombuffer(os.pread(f.fileno(), rows * W * 8, offset), np.float64)


def test_resident_maps_rows_go_to_disk_while_later_rows_decode(plan, stack, tmp_path,
                                                               monkeypatch):
    """A rig camera's maps (resident buffer): the rows the decoder reports final are written
    while it decodes the rest, each already as the finished maps hold it; the commit writes
    what is left and the file is the normal path's."""
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)
    options = DecodeOptions(chunk_pixels=W * 16)  # (ranges of 16 rows: bands final early)
    save_maps(_decoder(plan, stack, options).finish(dict(META)), tmp_path / "ref.npz")
    seen: list[tuple[int, np.ndarray]] = []
    with MapsFile(tmp_path / "maps.npz", (H, W), plan.axes(), resident=True) as out:
        def final_rows(rows: int) -> None:
            out.write_rows(rows)
            seen.append((rows, _x_on_disk(out, rows)))

        maps = _decoder(plan, stack, options).finish(dict(META), into=out.outputs(),
                                                     final_rows=final_rows)
        out.commit(maps, durable=False)
        out.recycle()
    assert [r for r, _ in seen][-1] == H and seen[0][0] < H  # rows went out before the end
    for rows, x in seen:
        whole = rows * W * 8 // 4096 * 4096 // 8  # (whole disk blocks of x)
        assert np.array_equal(x[:whole], maps.x.reshape(-1)[:whole], equal_nan=True), rows
    same_npz(tmp_path / "maps.npz", tmp_path / "ref.npz")


@pytest.mark.parametrize("refused_at", ["open", "write"])
def test_rows_go_through_the_page_cache_where_o_direct_is_refused(plan, stack, tmp_path,
                                                                  monkeypatch, refused_at):
    """A filesystem without O_DIRECT (tmpfs refuses the open; others refuse the first write
    with EINVAL): the rows and the rest are written through the page cache, same file."""
    from calibration.shared import maps_file

    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)
    options = DecodeOptions(chunk_pixels=W * 16)
    save_maps(_decoder(plan, stack, options).finish(dict(META)), tmp_path / "ref.npz")
    real_open, real_write, direct = os.open, maps_file.pwrite_all, set()

    def fake_open(path, flags, *args):
        if not flags & os.O_DIRECT:
            return real_open(path, flags, *args)
        if refused_at == "open":
            raise OSError(errno.EINVAL, "O_DIRECT refused")
        fd = real_open(path, flags & ~os.O_DIRECT, *args)
        direct.add(fd)
        return fd

    def fake_write(fd, data, offset):
        if fd in direct:
            raise OSError(errno.EINVAL, "unaligned for this filesystem")
        return real_write(fd, data, offset)

    monkeypatch.setattr(maps_file.os, "open", fake_open)
    monkeypatch.setattr(maps_file, "pwrite_all", fake_write)
    rows: list[int] = []
    with MapsFile(tmp_path / "maps.npz", (H, W), plan.axes(), resident=True) as out:
        def final_rows(n: int) -> None:
            out.write_rows(n)
            rows.append(n)

        maps = _decoder(plan, stack, options).finish(dict(META), into=out.outputs(),
                                                     final_rows=final_rows)
        out.commit(maps, durable=False)
        out.recycle()
    assert len(rows) >= 2 and (refused_at == "open" or direct)
    same_npz(tmp_path / "maps.npz", tmp_path / "ref.npz")


def test_rows_written_then_replaced_by_copied_maps_are_written_again(plan, stack, tmp_path):
    """Maps committed from arrays of their own (copied in) after `write_rows` wrote the
    buffer's rows: the copied members go to disk whole, not the stale blocks."""
    maps = _decoder(plan, stack).finish(dict(META))
    save_maps(maps, tmp_path / "ref.npz")
    with MapsFile(tmp_path / "maps.npz", (H, W), plan.axes(), resident=True) as out:
        for plane in out.outputs().values():
            plane[...] = 7  # what the buffer held before
        out.write_rows(H)
        out.commit(maps, durable=False)
        out.recycle()
    same_npz(tmp_path / "maps.npz", tmp_path / "ref.npz")


@pytest.mark.parametrize("resident", [False, True])
def test_live_decode_task_writes_the_maps_through_the_file(plan, stack, tmp_path,
                                                           monkeypatch, resident):
    """The live task (frames arriving in a frame store, staged in shared memory as a capture
    stores them) gives the file np.load reads, equal to decoding the same frames in memory.
    Mapped: unmapped only after the task returned (its ~0.03 s at 5 MP is not in the pose's
    ready time). Resident (a rig's cameras): written from a buffer (never mapped) that the
    worker keeps for its next pose. The reader releases the staged frames; with a cancel,
    nothing is left."""
    monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)
    write_plan(plan, tmp_path / "plan.json")
    pose, staged = tmp_path / "pose", tmp_path / "staged"
    staged.mkdir()
    store = FrameStore(pose, len(plan.frames), stage=True)
    store.add(0, stack[0])
    ctx = TaskContext("job_1")

    def feed() -> None:  # the capture: the other frames arrive while the task waits
        for i in range(1, len(plan.frames)):
            store.add(i, stack[i])

    feeder = threading.Timer(0.05, feed)
    feeder.start()
    RESIDENT.release()
    monkeypatch.setattr(tasks, "DROP_DELAY_S", 5.0)
    try:
        result = stream_decode_task(ctx, str(tmp_path / "plan.json"), str(pose),
                                    str(staged / "maps.npz"), meta=dict(META), durable=False,
                                    resident_maps=resident)
    finally:
        feeder.join()
        store.close()
    if resident:
        assert not _mapped(staged / "maps.npz")
        assert RESIDENT.kept_bytes() >= (staged / "maps.npz").stat().st_size - 4096
    else:  # mapped until after the task returned, then unmapped (no leak)
        assert _mapped(staged / "maps.npz") and RESIDENT.kept_bytes() == 0
        deadline = time.monotonic() + 60.0
        while _mapped(staged / "maps.npz") and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _mapped(staged / "maps.npz")
    assert not (pose / "frames.staging").exists()  # the reader said it was done
    # (the share prefaulted depends on the load: idle priority; the prefault's own test is
    # test_background_prefault_covers_the_regions_and_reports_its_error)
    assert 0.0 <= result["prefaulted"] <= 1.0
    assert [p.name for p in staged.iterdir()] == ["maps.npz"]
    save_maps(_decoder(plan, stack).finish(dict(META)), tmp_path / "ref.npz")
    same_npz(staged / "maps.npz", tmp_path / "ref.npz")

    class CancelledOnceLaidOut(TaskContext):
        def cancelled(self) -> bool:  # the job is cancelled once the maps file exists
            return any(staged.iterdir())

    (staged / "maps.npz").unlink()
    with pytest.raises(Cancelled):
        stream_decode_task(CancelledOnceLaidOut("job_2"), str(tmp_path / "plan.json"),
                           str(pose), str(staged / "maps.npz"))
    assert list(staged.iterdir()) == []


@pytest.mark.parametrize("compiled", [False, True])
def test_live_decode_task_takes_the_kernels_below_a_megapixel_only_when_asked(
        plan, stack, compiled, tmp_path, monkeypatch):
    """The service's long-lived workers ask for the compiled kernels at every image size
    (`compiled`); a one-off process (the CLI's capture) keeps the array path below 1 Mpixel.
    Either way the maps equal an in-memory decode that takes the same path."""
    ranges = []
    finish_range = decoder_module.finish_range
    monkeypatch.setattr(decoder_module, "finish_range",
                        lambda *a: ranges.append(1) or finish_range(*a))
    write_plan(plan, tmp_path / "plan.json")
    store = FrameStore(tmp_path / "pose", len(plan.frames))
    for i in range(len(plan.frames)):
        store.add(i, stack[i])
    store.close()
    stream_decode_task(TaskContext("job_1"), str(tmp_path / "plan.json"), str(tmp_path / "pose"),
                       str(tmp_path / "maps.npz"), meta=dict(META), compiled=compiled)
    assert bool(ranges) == compiled and H * W < decoder_module.COMPILED_MIN_PIXELS
    ref = StreamingDecoder(plan, (H, W), compiled=compiled)
    ref.prepare()
    ref.add_frames(list(range(stack.shape[0])), stack)
    save_maps(ref.finish(dict(META)), tmp_path / "ref.npz")
    same_npz(tmp_path / "maps.npz", tmp_path / "ref.npz")
