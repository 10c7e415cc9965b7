"""Small stacks for the maps-reference test: the decode benchmark's 64-frame plan seen by a
camera whose pixels sample the benchmark's 2448x2048 geometry on a coarse grid (every pixel
a different screen point), with camera noise, in the configurations the decoder has separate
paths for: unclipped, a clipped border, partly clipped steps; noise given or from residuals."""

from __future__ import annotations

import numpy as np

from acquisition.patterns import build_plan
from calibration.decode.noise import NoiseModel
from calibration.shared.plan import Plan, plan_from_dict

SHAPE = (40, 56)  # (H, W) of the small camera
FULL = (2048, 2448)  # the geometry it samples
READ_DN, GAIN = 0.6, 12.0  # camera noise: read std (DN), electrons per DN
# name -> (clipped border, partly clipped, noise given)
CONFIGS = {
    "plain_given": (False, False, True),
    "plain_residual": (False, False, False),
    "border_residual": (True, False, False),
    "partly_given": (False, True, True),
    "partly_residual": (False, True, False),
}


def reference_plan() -> Plan:
    """64 frames: 2 bright + 2 dark flats, 3 periods x 10 steps per axis."""
    base = build_plan(1920, 1080, 0.2745, steps=10, max_ratio=8.0, finest_period_px=48.0)
    data = base.to_dict()
    data["frames"] = [{"kind": "flat", "level": 1.0}, {"kind": "flat", "level": 0.0}] + data[
        "frames"]
    return plan_from_dict(data)


def black_dn(partly: bool) -> float:
    """The stacks' black level (DN)."""
    return 6.0 if partly else 20.0


def reference_stack(plan: Plan, border: bool, partly: bool, seed: int = 7,
                    shape: tuple[int, int] = SHAPE) -> np.ndarray:
    """uint8 (F, H, W) frames of `shape`; `partly`: a brightness rising across the image that
    clips the brightest steps of about a third of the pixels."""
    h, w = shape
    u = (np.arange(w, dtype=np.float32) * (FULL[1] / w))[None, :]
    v = (np.arange(h, dtype=np.float32) * (FULL[0] / h))[:, None]
    x = 0.75 * u + 0.05 * v
    y = 0.5 * v - 0.03 * u + 20.0
    black = black_dn(partly)
    gain = 280.0 * (0.6 + 0.4 * u / FULL[1]) if partly else 200.0
    rng = np.random.default_rng(seed)
    stack = np.empty((len(plan.frames), h, w), dtype=np.uint8)
    for i, f in enumerate(plan.frames):
        if f.kind == "flat":
            lin = np.full((h, w), f.level, dtype=np.float32)
        else:
            c = x if f.axis == "x" else y
            lin = 0.5 + 0.5 * np.cos(2 * np.pi * c / f.period_px + f.phase_shift)
        level = black + gain * lin
        level = level + rng.standard_normal((h, w), dtype=np.float32) * np.sqrt(
            READ_DN**2 + (level - black) / GAIN).astype(np.float32)
        stack[i] = np.clip(np.rint(level), 0.0, 255.0).astype(np.uint8)
        if border:
            stack[i, :, :6] = 0
            stack[i, :, -6:] = 0
    return stack


def reference_noise(partly: bool) -> NoiseModel:
    """The stacks' own camera noise model (the "noise given" configurations)."""
    return NoiseModel(read_dn=READ_DN, gain_e_per_dn=GAIN, black_dn=black_dn(partly))
