"""`phasecal decode`: stage timings, a folder read ahead in order, and a failed maps write
that leaves the previous maps file untouched (one-line error, exit 1), and the console
script's exit without teardown after a decode."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from acquisition.patterns import build_plan
from api.cli import main as cli_main
from calibration.decode import read_frames
from calibration.shared.maps import load_maps
from calibration.shared.plan import Plan, write_plan
from tests.calibration.shared.test_npz_store import disk_full_on_write

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def plan() -> Plan:
    return build_plan(640, 480, 0.2745, steps=4)


def _stack(plan: Plan, h: int = 48, w: int = 64) -> np.ndarray:
    """Frames of a screen seen 1:1 with an offset (mid-grey flats, clean fringes)."""
    u = np.arange(w, dtype=np.float64)[None, :] + 100.0
    v = np.arange(h, dtype=np.float64)[:, None] + 80.0
    frames = []
    for f in plan.frames:
        if f.kind == "flat":
            lin = np.full((h, w), f.level)
        else:
            c = u if f.axis == "x" else v
            lin = 0.5 + 0.5 * np.cos(2 * np.pi * c / f.period_px + f.phase_shift)
        frames.append(np.round(20 + 200 * np.broadcast_to(lin, (h, w))).astype(np.uint8))
    return np.stack(frames)


def _args(tmp_path: Path, frames: Path, out: Path, *extra: str) -> list[str]:
    return ["decode", "--plan", str(tmp_path / "plan.json"), "--frames", str(frames),
            "--noise-dn", "1.0", "-o", str(out), *extra]


def test_timings_line_and_maps_written(plan, tmp_path):
    """A fresh process (the way users run it): the maps load, stderr has the stage line."""
    write_plan(plan, tmp_path / "plan.json")
    np.save(tmp_path / "frames.npy", _stack(plan))
    out = tmp_path / "maps.npz"
    run = subprocess.run([sys.executable, "-m", "api.cli",
                          *_args(tmp_path, tmp_path / "frames.npy", out, "--timings")],
                         cwd=ROOT, capture_output=True, text=True, check=True)
    line = run.stderr.strip().splitlines()[-1]
    for stage in ("imports", "read+decode", "write", "fsync", "total", "CPU"):
        assert stage in line, line
    maps = load_maps(out)
    assert maps.shape == (48, 64) and maps.valid_count() > 0.9 * 48 * 64
    assert "pixels valid" in run.stdout


@pytest.mark.parametrize("compiled", [False, True])
def test_npy_stack_decoded_into_the_laid_out_file(plan, tmp_path, monkeypatch, compiled):
    """A `.npy` stack is decoded straight into the maps file laid out before the decoder's
    imports: every member equal to the library's decode written by `save_maps`."""
    import calibration.decode.decoder as decoder_module
    from calibration.decode import decode_stack
    from calibration.shared.maps import save_maps
    from tests.calibration.shared.npz_checks import same_npz

    if compiled:  # (the compiled whole-stack path of large images)
        monkeypatch.setattr(decoder_module, "COMPILED_MIN_PIXELS", 0)
        monkeypatch.setattr(decoder_module, "ALWAYS_COMPILED_PIXELS", 0)
    write_plan(plan, tmp_path / "plan.json")
    stack = _stack(plan)
    np.save(tmp_path / "frames.npy", stack)
    assert cli_main(_args(tmp_path, tmp_path / "frames.npy", tmp_path / "maps.npz")) == 0
    ref = decode_stack(plan, stack, noise=1.0, meta={"frames": str(tmp_path / "frames.npy")})
    save_maps(ref, tmp_path / "ref.npz")
    same_npz(tmp_path / "maps.npz", tmp_path / "ref.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames.npy", "maps.npz", "plan.json",
                                                          "ref.npz"]


def _full_at_reserve(monkeypatch: pytest.MonkeyPatch) -> None:
    def full(fd, offset, length):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full, raising=False)


@pytest.mark.parametrize("full", [lambda mp: disk_full_on_write(mp, 1), _full_at_reserve],
                         ids=["at the last write", "when the maps file is laid out"])
def test_failed_write_keeps_previous_maps(plan, tmp_path, monkeypatch, capsys, full):
    """A `.npy` stack's maps file is laid out before the decode (`MapsFile`): a full disk
    when its space is reserved or when its directory is written keeps the previous maps."""
    write_plan(plan, tmp_path / "plan.json")
    np.save(tmp_path / "frames.npy", _stack(plan))
    out = tmp_path / "maps.npz"
    out.write_bytes(b"previous maps")
    full(monkeypatch)
    assert cli_main(_args(tmp_path, tmp_path / "frames.npy", out)) == 1
    err = capsys.readouterr().err.strip()
    assert "maps.npz" in err and "No space left" in err and "\n" not in err
    assert out.read_bytes() == b"previous maps"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames.npy", "maps.npz", "plan.json"]


def test_folder_frames_read_ahead_in_plan_order(plan, tmp_path):
    """Images decoded by several threads still come out in frame order, and a frame of the
    wrong size is reported with its file name."""
    import cv2

    stack = _stack(plan)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, f in enumerate(stack):
        cv2.imwrite(str(folder / f"frame_{i:04d}.png"), f)
    got = list(read_frames(folder))
    assert len(got) == len(stack) and all(np.array_equal(a, b) for a, b in
                                          zip(got, stack, strict=True))
    cv2.imwrite(str(folder / "frame_0007.png"), stack[7][:, :32])
    with pytest.raises(ValueError, match=r"frame_0007\.png"):
        list(read_frames(folder))


def test_folder_read_into_one_array_when_it_fits(plan, tmp_path, monkeypatch):
    """A folder that fits in memory is read once into an (F, H, W) array (the decoder's
    whole-stack path); iterating afterwards yields it without reading the files again; a
    folder too large for memory streams (array() is None)."""
    import cv2

    from calibration.decode import frames_io

    stack = _stack(plan)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, f in enumerate(stack):
        cv2.imwrite(str(folder / f"frame_{i:04d}.png"), f)
    source = read_frames(folder)
    whole = source.array()
    assert whole is not None and whole.shape == stack.shape and np.array_equal(whole, stack)
    for f in folder.iterdir():
        f.unlink()
    assert all(np.array_equal(a, b) for a, b in zip(source, stack, strict=True))
    monkeypatch.setattr(frames_io, "_memory_bytes", lambda: stack.nbytes)  # 4x too small
    for i, f in enumerate(stack):
        cv2.imwrite(str(folder / f"frame_{i:04d}.png"), f)
    assert read_frames(folder).array() is None


@pytest.mark.parametrize("failing", [False, True])
def test_console_exits_without_teardown_only_after_a_decode(plan, tmp_path, monkeypatch,
                                                            failing):
    """The console script skips the interpreter's teardown after `decode` returns (maps
    durable by then) with the command's status; not after an error, nor for other commands."""
    import api.cli

    exits: list[int] = []
    monkeypatch.setattr(api.cli, "_exit_now", exits.append)
    write_plan(plan, tmp_path / "plan.json")
    frames = tmp_path / "frames.npy"
    np.save(frames, _stack(plan)[:-1] if failing else _stack(plan))
    code = cli_main(_args(tmp_path, frames, tmp_path / "maps.npz"), exit_now=True)
    assert (code, exits) == ((1, []) if failing else (0, [0]))
    assert cli_main(["plan", "-o", str(tmp_path / "p.json")], exit_now=True) == 0
    assert exits == ([] if failing else [0])
