"""Rendering speed of the simulated optics and sensor (hw_mocks): setup, frame, exposure.

Run: .venv/bin/python benchmarks/hw_mocks_optics.py  (prints a table; median of repeats)
"""

from __future__ import annotations

import time

import numpy as np

from acquisition.patterns import frame_linear
from calibration.shared.plan import CosineFrame, FlatFrame, Plan, ScreenGeometry
from hw_mocks.cameras import mild_pinhole, smooth_noncentral, wide_fisheye
from hw_mocks.optics import OpticalSetup
from hw_mocks.poses import random_poses
from hw_mocks.sensor import SensorModel

SCREEN = ScreenGeometry(1920, 1080, (0.2745, 0.2745))
SIZES = ((640, 480), (2448, 2048))
REPEATS = 5


def _median_s(fn, repeats: int = REPEATS) -> float:
    """Median wall time of `fn()` in seconds."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    """Print setup / render / expose times for each camera and size."""
    plan = Plan(
        SCREEN, (CosineFrame("x", 24.0, 1, 8), CosineFrame("y", 24.0, 1, 8), FlatFrame(1.0))
    )
    torn = frame_linear(plan, 0)
    torn[: SCREEN.height_px // 3] = frame_linear(plan, 2)[: SCREEN.height_px // 3]
    images = {
        "cos-x": frame_linear(plan, 0),
        "cos-y": frame_linear(plan, 1),
        "flat": frame_linear(plan, 2),
        "torn": torn,  # not separable: general 2-D sampling path
    }
    sensor = SensorModel(bit_depth=12)
    rng = np.random.default_rng(0)
    print(
        f"{'camera':<12} {'size':>10} {'blur':>5} {'setup s':>8} "
        + " ".join(f"{k + ' ms':>10}" for k in images)
        + f" {'expose ms':>10}"
    )
    for w, h in SIZES:
        for name, make in (
            ("pinhole", mild_pinhole),
            ("fisheye", wide_fisheye),
            ("noncentral", smooth_noncentral),
        ):
            cam = make(w, h)
            pose = random_poses(cam, SCREEN, 1, np.random.default_rng(1))[0]
            for blur in (0.0, 2.0):
                setup = OpticalSetup(cam, pose, SCREEN, blur_sigma_screen_px=blur)
                t_setup = _median_s(setup.truth, 1)
                cols = [
                    _median_s(lambda im=im, s=setup: s.render_irradiance(im)) * 1e3
                    for im in images.values()
                ]
                irr = setup.render_irradiance(images["cos-x"])
                t_exp = _median_s(lambda irr=irr: sensor.expose(irr, 0.02, 0.0, rng)) * 1e3
                print(
                    f"{name:<12} {f'{w}x{h}':>10} {blur:>5.1f} {t_setup:>8.2f} "
                    + " ".join(f"{c:>10.1f}" for c in cols)
                    + f" {t_exp:>10.1f}"
                )


if __name__ == "__main__":
    main()
