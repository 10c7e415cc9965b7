"""Honest sigma on every camera: normalized decode errors on an independent renderer.

Renders the default plan (and the `fast` 6-step plan) with the tests' independent renderer
(tests/calibration/decode/independent_render.py: its own fisheye/pinhole/non-central
projection, 4x4 pixel-area sub-samples, Poisson shot noise, read noise, black level,
vignetting, 8-bit quantization with clipping, a monitor with gamma 2.2 and an 8-bit LUT),
decodes with the noise estimated from the residuals (`noise=None`, as `phasecal decode`
without `--noise-dn`) and with the sensor's true noise model, and prints the std of
(decoded - truth) / sigma over valid pixels, per radial band for residual mode, and the
count beyond 5 sigma. Rerun: `.venv/bin/python -P benchmarks/sigma_honesty.py` (~1 min).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from acquisition.patterns import build_plan
from calibration.decode import NoiseModel, decode_stack
from tests.calibration.decode.independent_render import (
    Camera,
    Monitor,
    Scene,
    Sensor,
    normalized_errors,
    render,
)

FISHEYE = Scene(Camera(160, 120, stride=8), sensor=Sensor(gain_e_per_dn=20.0, read_dn=0.35))
SCENES: dict[str, Scene] = {
    "fisheye150 read0.5": replace(FISHEYE, sensor=Sensor(read_dn=0.5)),
    "fisheye150 read0.35": FISHEYE,
    "fisheye150 dim g100 read0.2": replace(
        FISHEYE, sensor=Sensor(gain_e_per_dn=100.0, read_dn=0.2), peak_e=3000.0),
    "fisheye150 g10 read0.3": replace(
        FISHEYE, sensor=Sensor(gain_e_per_dn=10.0, read_dn=0.3), peak_e=2000.0),
    "fisheye150 vignetting g5": replace(
        FISHEYE, sensor=Sensor(gain_e_per_dn=5.0, read_dn=0.4), peak_e=1000.0, vignetting=1.0),
    "fisheye150 black0": replace(FISHEYE, sensor=Sensor(black_dn=0.0, read_dn=0.3)),
    "fisheye150 small screen": replace(FISHEYE, distance_mm=400.0),
    "fisheye150 overexposed": replace(FISHEYE, peak_e=6000.0),
    "fisheye150 gamma no LUT": replace(FISHEYE, monitor=Monitor(lut=False)),
    "fisheye150 no LUT, vignetted": replace(FISHEYE, monitor=Monitor(lut=False),
                                            vignetting=0.25),
    "fisheye150 non-central": replace(
        FISHEYE, camera=Camera(160, 120, stride=8, pupil_shift_mm=2.0)),
    "pinhole 50": replace(FISHEYE, camera=Camera(160, 120, fov_deg=50.0, kind="pinhole",
                                                 stride=8), distance_mm=700.0),
    "wide pinhole 100": replace(FISHEYE, camera=Camera(160, 120, fov_deg=100.0, kind="pinhole",
                                                       stride=8), distance_mm=250.0),
}


def line(name: str, scene: Scene, preset: str, seed: int) -> str:
    plan = build_plan(1920, 1080, scene.pitch_mm, preset=preset)
    stack, truth = render(scene, plan, seed)
    s = scene.sensor
    model = NoiseModel(read_dn=s.read_dn, gain_e_per_dn=s.gain_e_per_dn, black_dn=s.black_dn)
    maps = decode_stack(plan, stack)
    z, r = normalized_errors(maps, truth)
    zm, _ = normalized_errors(decode_stack(plan, stack, noise=model), truth)
    bands = [z[(r >= a) & (r < b)] for a, b in ((0, 0.3), (0.3, 0.6), (0.6, 0.9), (0.9, 9))]
    band = " ".join(f"{b.std():.2f}" if b.size > 100 else "  - " for b in bands)
    ptc = maps.meta["decoder"]["photon_transfer"]
    return (f"{name:30s} {preset:7s} {z.size:6d} {z.std():6.3f} {zm.std():6.3f}  {band}  "
            f"{int(np.sum(np.abs(z) > 5)):3d} {int(np.sum(np.abs(zm) > 5)):3d}  "
            f"{ptc['offset']:+.3f} {ptc['slope']:.4f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--presets", default="default,fast")
    args = parser.parse_args()
    t0 = time.process_time()
    print(f"{'scene':30s} {'plan':7s} {'n':>6s} {'std':>6s} {'model':>6s}  "
          "radial bands      >5 (res, model)  line offset, slope")
    for preset in args.presets.split(","):
        for name, scene in SCENES.items():
            print(line(name, scene, preset, args.seed), flush=True)
    print(f"cpu {time.process_time() - t0:.0f} s")


if __name__ == "__main__":
    main()
