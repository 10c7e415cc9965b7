"""Streaming phase-shift decoder: frames of one pose -> per-pixel screen points with uncertainty.

Public API: `StreamingDecoder` (a `FrameSink`), `decode_stack`, `DecodeOptions`,
`NoiseModel`, `DecodeError`, `read_frames`. Method and rules: docs/decoder.md.
"""

from calibration.decode.accumulate import DecodeError
from calibration.decode.decoder import StreamingDecoder
from calibration.decode.frames_io import FrameSource, read_frames
from calibration.decode.noise import NoiseModel
from calibration.decode.options import DecodeOptions
from calibration.decode.stack import decode_stack
from calibration.decode.validity import REASONS

__all__ = [
    "REASONS",
    "DecodeError",
    "DecodeOptions",
    "FrameSource",
    "NoiseModel",
    "StreamingDecoder",
    "decode_stack",
    "read_frames",
]
