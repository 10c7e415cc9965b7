"""`phasecal decode`: decode one pose's captured frames into `phasecal.maps/1` maps (NPZ)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from typing import Any

from api.cli import UserError
from api.progress import progress_bar
from calibration.readahead import prefetch

# The maps are written, fsynced and renamed when `run` returns: the console script then
# exits without the interpreter's teardown of the loaded kernels (api.cli `_exit_now`).
EXIT_WITHOUT_TEARDOWN = True


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plan", required=True, help="pattern plan (phasecal.plan/1 JSON)")
    p.add_argument(
        "--frames", required=True, help="(F, H, W) .npy stack, or a folder of frame_NNNN images"
    )
    p.add_argument(
        "--noise-dn", type=float, metavar="SIGMA",
        help="per-frame camera noise sigma in DN (default: estimated from the fit residuals)",
    )
    p.add_argument(
        "--saturation-dn", type=float,
        help="clipping level in DN (default: the maximum of the frame dtype)",
    )
    p.add_argument(
        "--max-sigma-px", type=float, help="largest accepted 1-sigma in screen px (default 1)"
    )
    p.add_argument("-o", "--output", required=True, help="output maps.npz")
    p.add_argument("--timings", action="store_true",
                   help="print each stage's wall seconds and the CPU seconds on stderr")


class _Stages:
    """Wall seconds of the command's stages, printed on stderr with `--timings`."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self._t0 = self._last = time.perf_counter()
        self._cpu0 = time.process_time()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.wall[name] = now - self._last
        self._last = now

    def report(self) -> str:
        """One line: each stage's seconds, the total, and the process's CPU seconds."""
        parts = " ".join(f"{k} {v:.3f}" for k, v in self.wall.items())
        return (f"timings (wall s): {parts} total {time.perf_counter() - self._t0:.3f}; "
                f"CPU {time.process_time() - self._cpu0:.3f} s")


def _laid_out(args: argparse.Namespace) -> Any:
    """For one `.npy` stack: the output `MapsFile`, laid out from the stack's header and the
    plan's axes before the decoder's imports (its pages are then faulted in by a thread at
    idle priority, on the core the single-threaded imports leave free); the decoder writes
    into it. None otherwise, or where the inputs are bad (the decode says why)."""
    # lazy: NumPy and the maps writer load while the stack streams in (prefetch in `run`)
    import numpy as np

    from calibration.shared.maps_file import MapsFile
    from calibration.shared.plan import read_plan

    if not str(args.frames).endswith(".npy") or os.name != "posix":
        return None  # (Windows cannot rename a file that is still mapped)
    try:
        shape = np.load(args.frames, mmap_mode="r").shape
        axes = read_plan(args.plan).axes()
    except (OSError, ValueError, EOFError):
        return None
    if len(shape) != 3 or min(shape) < 1:
        return None
    try:
        out = MapsFile(args.output, shape[1:], axes)
    except OSError as exc:  # disk full, no such folder: the previous file stays as it was
        raise UserError(f"{args.output}: cannot write the maps ({exc})") from None
    return out


def run(args: argparse.Namespace) -> int:
    stages = _Stages()
    prefetch(args.frames)  # a cold stack streams in while NumPy and the kernels load
    out = _laid_out(args)
    if out is None:
        return _decode(args, stages, None, None)
    from calibration.shared.maps_file import prefaulted  # lazy: imports NumPy (see _laid_out)

    with prefaulted(out) as ahead:
        return _decode(args, stages, out, ahead)


def _decode(args: argparse.Namespace, stages: _Stages, out: Any, ahead: Any) -> int:
    """Decode and write the maps (into `out` when laid out, its pages faulted in `ahead`),
    then print the summary."""
    # lazy: the decoder and its kernels load while the stack streams in
    import numpy as np

    from calibration import DecodeOptions, decode_frames
    from calibration.shared.maps import save_maps
    from calibration.shared.plan import read_plan

    stages.lap("imports")
    plan = read_plan(args.plan)
    if args.noise_dn is not None and not args.noise_dn > 0:
        raise UserError(f"--noise-dn: must be > 0 DN, got {args.noise_dn}")
    options = DecodeOptions()
    if args.max_sigma_px is not None:
        options = replace(options, max_sigma_px=args.max_sigma_px)
    stages.lap("plan")
    written: dict[str, float] = {}
    try:
        if ahead is not None:
            ahead.stop()  # what is left, the decoder's threads fault in
    except OSError as exc:
        raise UserError(f"{args.output}: cannot write the maps ({exc})") from None
    with progress_bar("decode") as update:
        maps = decode_frames(plan, args.frames, noise=args.noise_dn,
                             saturation_dn=args.saturation_dn, options=options,
                             meta={"frames": str(args.frames)}, progress=update,
                             into=None if out is None else out.outputs())
    stages.lap("read+decode")
    try:
        if out is None:
            save_maps(maps, args.output, timings=written)
        else:
            out.commit(maps, timings=written)
    except OSError as exc:  # disk full, no permission: the previous file stays as it was
        raise UserError(f"{args.output}: cannot write the maps ({exc})") from None
    stages.lap("save")
    save = stages.wall.pop("save")
    stages.wall.update(written)
    stages.wall["rename"] = save - sum(written.values())  # and the folder's fsync
    h, w = maps.shape
    valid = maps.valid_count()
    med = (float(np.median(maps.sigma_x[maps.mask], overwrite_input=True)) if valid
           else float("nan"))
    print(
        f"wrote {args.output}: {valid} of {h * w} pixels valid "
        f"({100.0 * valid / (h * w):.1f} %), median sigma_x {med:.3g} px"
    )
    stages.lap("summary")
    if args.timings:
        print(stages.report(), file=sys.stderr)
    return 0
