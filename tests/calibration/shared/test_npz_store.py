"""The parallel stored-NPZ writer: a valid zip (CRCs, zip64 records) that np.load reads back
exactly, fsynced before the rename, and never a partial file at the destination."""

import json
import os
import subprocess
import sys
import textwrap
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from calibration.shared import npz_store
from calibration.shared.npz_store import write_npz_stored

ROOT = Path(__file__).resolve().parents[3]


def disk_full_on_write(monkeypatch: pytest.MonkeyPatch, nth: int) -> None:
    """Make the `nth` os.pwrite of this test fail as a full disk would (ENOSPC)."""
    real_pwrite, count = os.pwrite, [0]

    def pwrite(fd, data, offset):
        count[0] += 1
        if count[0] == nth:
            raise OSError(28, "No space left on device")
        return real_pwrite(fd, data, offset)

    monkeypatch.setattr(os, "pwrite", pwrite)


def _arrays(n: int = 64) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    return {
        "x": rng.uniform(0, 1000, (n, n + 3)),
        "mask": rng.uniform(size=(n, n + 3)) > 0.3,
        "sigma_x": rng.uniform(size=(n + 3, n)).astype(np.float32).T,  # not C-contiguous
        "empty": np.zeros((0, 4), np.float32),
        "meta": np.array(json.dumps({"format": "phasecal.maps/1", "note": "é"})),
    }


def _check(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with zipfile.ZipFile(path) as zf:
        assert zf.testzip() is None  # every member's CRC matches
        assert [i.filename for i in zf.infolist()] == [f"{k}.npy" for k in arrays]
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_STORED}
    with np.load(path, allow_pickle=False) as npz:
        for key, want in arrays.items():
            got = npz[key]
            assert got.dtype == want.dtype and got.shape == want.shape, key
            assert got.tobytes() == np.ascontiguousarray(want).tobytes(), key


def test_members_read_back_exactly(tmp_path):
    arrays = _arrays()
    write_npz_stored(tmp_path / "a.npz", arrays)
    _check(tmp_path / "a.npz", arrays)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]  # no temp file left


def test_zip64_records_when_offsets_and_sizes_exceed_the_limit(tmp_path, monkeypatch):
    """Above 2 GiB members need zip64 extras and end records; a small limit exercises them."""
    monkeypatch.setattr(npz_store, "_LIMIT", 1000)
    arrays = _arrays()
    write_npz_stored(tmp_path / "big.npz", arrays)
    raw = (tmp_path / "big.npz").read_bytes()
    assert zipfile.stringEndArchive64 in raw and zipfile.stringEndArchive64Locator in raw
    _check(tmp_path / "big.npz", arrays)


def test_fsync_before_rename_then_folder_fsync(tmp_path, monkeypatch):
    calls: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        calls.append("fsync dir" if os.path.isdir(f"/proc/self/fd/{fd}") else "fsync file")
        real_fsync(fd)

    def replace(src, dst) -> None:
        calls.append("rename")
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    timings: dict[str, float] = {}
    write_npz_stored(tmp_path / "a.npz", _arrays(), timings)
    assert calls == ["fsync file", "rename", "fsync dir"]
    assert set(timings) == {"write", "fsync"}


def test_failure_mid_write_leaves_the_old_file_and_no_temp(tmp_path, monkeypatch):
    """A write error (disk full) after some members landed: the destination keeps its old
    content, the temporary file is removed, the error reaches the caller."""
    dest = tmp_path / "maps.npz"
    dest.write_bytes(b"old maps")
    disk_full_on_write(monkeypatch, 4)
    with pytest.raises(OSError, match="No space left"):
        write_npz_stored(dest, _arrays())
    assert dest.read_bytes() == b"old maps"
    assert [p.name for p in tmp_path.iterdir()] == ["maps.npz"]


def test_killed_writer_never_leaves_a_partial_file_at_the_destination(tmp_path):
    """SIGKILL while members are being written (each pwrite slowed down): nothing at the
    destination, only the hidden temporary file that a later write does not depend on."""
    script = textwrap.dedent(f"""
        import os, sys, time
        import numpy as np
        from calibration.shared.npz_store import write_npz_stored
        real = os.pwrite
        def slow(fd, data, offset):
            n = real(fd, data, offset)
            print("wrote", flush=True)
            time.sleep(0.2)
            return n
        os.pwrite = slow
        write_npz_stored({str(tmp_path / "maps.npz")!r},
                         {{f"m{{i}}": np.ones(1000) for i in range(40)}})
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().startswith("wrote")
        time.sleep(0.1)
        assert proc.poll() is None  # still writing
    finally:
        proc.kill()
        proc.wait()
    assert not (tmp_path / "maps.npz").exists()
    leftovers = [p.name for p in tmp_path.iterdir()]
    assert len(leftovers) == 1 and leftovers[0].startswith(".maps.")
    write_npz_stored(tmp_path / "maps.npz", _arrays())  # a rerun writes a complete file
    _check(tmp_path / "maps.npz", _arrays())


def test_object_arrays_are_refused(tmp_path):
    with pytest.raises(ValueError, match="bad: object arrays"):
        write_npz_stored(tmp_path / "a.npz", {"bad": np.array([None, 1], dtype=object)})
    assert list(tmp_path.iterdir()) == []


def test_not_durable_skips_the_fsyncs_but_still_renames_whole(tmp_path, monkeypatch):
    synced: list[int] = []
    monkeypatch.setattr(os, "fsync", synced.append)
    arrays = _arrays()
    write_npz_stored(tmp_path / "a.npz", arrays, durable=False)
    assert synced == []
    _check(tmp_path / "a.npz", arrays)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]


def test_without_pwrite_or_sync_file_range(tmp_path, monkeypatch):
    """Where the OS has neither (Windows): seek + write under a lock, same file."""
    monkeypatch.delattr(os, "pwrite")
    monkeypatch.setattr(npz_store, "_start_writeback", lambda: lambda fd, offset, length: None)
    arrays = _arrays()
    write_npz_stored(tmp_path / "a.npz", arrays)
    _check(tmp_path / "a.npz", arrays)
