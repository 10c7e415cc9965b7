"""Processes of one install compile the decoder's kernels one at a time (the others wait and
load the cache), and once compiled nobody waits on the lock any more."""

from __future__ import annotations

import fcntl
import subprocess
import sys
import time
from pathlib import Path

from calibration.decode.kernel_warm import compiled_once

# a process that "compiles" (sleeps) inside compiled_once and logs when it was in the body
_ENTER = """
import sys, time
from calibration.decode.kernel_warm import compiled_once
folder, log, pause = sys.argv[1], sys.argv[2], float(sys.argv[3])
with compiled_once(folder):
    start = time.time()
    time.sleep(pause)
    with open(log, "a") as f:
        f.write(f"{start} {time.time()}\\n")
"""


def _start(tmp_path: Path, pause: float) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", _ENTER, str(tmp_path / "cache"),
                             str(tmp_path / "log"), str(pause)], cwd=Path(__file__).parents[3])


def _waiting_on(lock: Path) -> int:
    """Processes blocked on `lock`'s flock (/proc/locks lists waiters with '->')."""
    inode = f":{lock.stat().st_ino} "
    return sum(1 for line in Path("/proc/locks").read_text().splitlines()
               if "->" in line and inode in line)


def test_one_process_compiles_at_a_time_then_none_waits(tmp_path: Path) -> None:
    (tmp_path / "cache").mkdir()
    lock = tmp_path / "cache" / "kernels.lock"
    with open(lock, "a") as held:  # hold it until both processes wait for it
        fcntl.flock(held, fcntl.LOCK_EX)
        procs = [_start(tmp_path, 0.5) for _ in range(2)]
        deadline = time.monotonic() + 120  # (a hang guard, not a timing check)
        while _waiting_on(lock) < 2:
            assert all(p.poll() is None for p in procs), "a process did not wait for the lock"
            assert time.monotonic() < deadline, "the processes never waited for the lock"
            time.sleep(0.05)
    assert [p.wait(120) for p in procs] == [0, 0]
    (first, second) = sorted(tuple(map(float, line.split()))
                             for line in (tmp_path / "log").read_text().splitlines())
    assert first[1] <= second[0]  # one after the other
    assert (tmp_path / "cache" / "kernels.warm").is_file()
    # compiled: a process enters while another holds the lock (it would wait forever)
    with open(lock, "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        assert _start(tmp_path, 0.0).wait(120) == 0
    assert len((tmp_path / "log").read_text().splitlines()) == 3


def test_a_failed_compile_leaves_no_mark_and_no_lock(tmp_path: Path) -> None:
    try:
        with compiled_once(tmp_path):
            raise RuntimeError("compile failed")
    except RuntimeError:
        pass
    assert not (tmp_path / "kernels.warm").exists()
    with open(tmp_path / "kernels.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)  # free again


def test_without_a_folder_the_body_just_runs() -> None:
    ran = []
    with compiled_once(None):
        ran.append(1)
    assert ran == [1]
