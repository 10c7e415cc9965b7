"""Parametric calibration benchmark: accuracy vs ground truth, noise-floor ratio and wall time.

Run: .venv/bin/python benchmarks/calibrate.py
"""

from __future__ import annotations

import time

import numpy as np

from calibration.fit.dispatch import calibrate
from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import mild_pinhole, wide_fisheye
from hw_mocks.poses import random_poses
from hw_mocks.synthetic import synthetic_maps

SCREEN = ScreenGeometry(1920, 1080, (0.2745, 0.2745))
SIGMA = 0.05


def _data(cam, n: int, seed: int):
    """n posed synthetic maps (2 % gross outliers) of a truth camera."""
    rng = np.random.default_rng(seed)
    poses = random_poses(cam, SCREEN, n, rng)
    return [synthetic_maps(cam, p, SCREEN, sigma_px=SIGMA, rng=rng, outlier_fraction=0.02)[0]
            for p in poses]


def main() -> None:
    """Fit each model to each camera and print one table row per fit."""
    cams = {"mild_pinhole": mild_pinhole(), "fisheye150": wide_fisheye(fov_deg=150)}
    print(f"{'camera':<13} {'model':<16} {'pts/pose':>8} {'f err %':>8} {'rms px':>8} "
          f"{'floor px':>8} {'ratio':>7} {'held px':>8} {'wall s':>7}")
    for cname, cam in cams.items():
        maps = _data(cam, 9, 5)
        f_true = getattr(cam, "fx", getattr(cam, "f", np.nan))
        for model in ("opencv5", "opencv-rational", "fisheye"):
            for cap in (500, 2000):
                t0 = time.perf_counter()
                res = calibrate(maps, SCREEN, model, heldout=[8],
                                options={"max_points_per_pose": cap})
                wall = time.perf_counter() - t0
                st = res.stats
                f_err = 100 * (res.model.get_params()[0] / f_true - 1)
                print(f"{cname:<13} {model:<16} {cap:>8} {f_err:>8.3f} {st['rms_px']:>8.4f} "
                      f"{st['expected_rms_px']:>8.4f} {st['noise_floor_ratio']:>7.2f} "
                      f"{st['heldout']['rms_px']:>8.4f} {wall:>7.2f}")


if __name__ == "__main__":
    main()
