"""`decode_stack`: the one decode loop over a pose's frames, for every front end."""

from __future__ import annotations

from types import ModuleType
from typing import Any

import numpy as np

from calibration.decode.accumulate import DecodeError
from calibration.decode.decoder import StreamingDecoder, one_shot_compiled
from calibration.decode.frames_io import FrameSource
from calibration.decode.noise import NoiseModel, NoiseSource
from calibration.decode.options import DecodeOptions
from calibration.shared.maps import DecodedMaps
from calibration.shared.plan import Plan
from calibration.shared.progress import CancelCheck, Cancelled, ProgressFn


def _whole(frames: Any) -> np.ndarray | None:
    """The frames as one (F, H, W) array when they are one (an array or a `.npy` stack)."""
    if isinstance(frames, FrameSource):
        return frames.array()
    if isinstance(frames, np.ndarray) and frames.ndim == 3:
        return frames
    return None


def decode_stack(
    plan: Plan,
    frames: Any,
    *,
    noise: NoiseModel | NoiseSource | float | None = None,
    saturation_dn: float | None = None,
    options: DecodeOptions | None = None,
    xp: ModuleType | str | None = np,
    meta: dict[str, Any] | None = None, progress: ProgressFn | None = None,
    cancelled: CancelCheck | None = None, prepare: bool = False,
    into: dict[str, np.ndarray] | None = None,
) -> DecodedMaps:
    """The one decode loop: frames in plan order (an (F, H, W) stack, a `FrameSource` or any
    sized iterable of 2-D frames) to maps; progress per frame, `Cancelled` between frames.

    A whole NumPy stack (large enough for the kernels to pay back their loading,
    `one_shot_compiled`; any size with `prepare`: a long-lived process loads them once) is
    decoded range by range with the compiled kernels
    (`StreamingDecoder.finish_stack`). `into`: the arrays to decode into
    (`StreamingDecoder.finish`)."""
    count = len(frames)
    if count != len(plan.frames):
        raise DecodeError(f"frames: {count} frames given, the plan has {len(plan.frames)} "
                          "(frame i must be captured while plan frame i was shown)")
    whole = _whole(frames)
    if whole is not None and whole.shape[0] == count:
        kernels = prepare or one_shot_compiled(whole.shape[1] * whole.shape[2], noise)
        dec = StreamingDecoder(plan, tuple(whole.shape[1:]), noise=noise,
                               saturation_dn=saturation_dn, options=options, xp=xp,
                               compiled=kernels)
        if dec.uses_kernels and kernels:
            # the kernels' modules; numba loads the machine code of the argument types
            # this stack needs at their first call (cheaper than warming every variant)
            import calibration.decode.accumulate_kernel
            import calibration.decode.kernel_sums  # noqa: F401
        if dec.compiled_now:
            def step(fraction: float) -> None:
                if cancelled is not None and cancelled():
                    raise Cancelled(f"decode cancelled at {fraction:.0%}")
                if progress is not None:
                    progress(round(fraction * count), count, "decode")

            step(0.0)
            # unobserved (no progress, no cancellation): every range in one parallel pass,
            # without a wait for the slowest range of each sixteenth
            watched = progress is not None or cancelled is not None
            maps = dec.finish_stack(whole, meta, step if watched else None, into)
            if progress is not None:
                progress(count, count, "unwrap")
            return maps
    dec = None
    for i, frame in enumerate(frames):
        if cancelled is not None and cancelled():
            raise Cancelled(f"decode cancelled after {i} of {count} frames")
        if dec is None:
            if getattr(frame, "ndim", None) != 2:
                raise DecodeError("frames: expected a (F, H, W) stack of single-channel frames, "
                                  f"got frame shape {getattr(frame, 'shape', None)}")
            dec = StreamingDecoder(plan, tuple(frame.shape), noise=noise,
                                   saturation_dn=saturation_dn, options=options, xp=xp,
                                   compiled=prepare)
            if prepare:
                dec.prepare()
        dec.add(i, frame)
        if progress is not None:
            progress(i + 1, count, "decode")
    assert dec is not None  # count == len(plan.frames) > 0
    if progress is not None:
        progress(count, count, "unwrap")
    return dec.finish(meta, into)
