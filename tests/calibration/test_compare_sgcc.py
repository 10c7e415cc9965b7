"""Two sGCC fits compared after their best rotation, each with its ray sigma without the
rotation-like part: fits of the same simulated camera from disjoint poses agree within
their uncertainty; a fit of the same lens with a changed radial term does not."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from calibration.fit.dispatch import calibrate
from calibration.report_diff import write_diff
from calibration.report_draw import ray_sigma_map
from calibration.shared.plan import ScreenGeometry
from hw_mocks import cameras, poses, synthetic

W, H = 160, 120
SCREEN = ScreenGeometry(1920, 1080, (0.2745, 0.2745))
POSES_PER_FIT = 6


def _fit(camera, rng: np.random.Generator, pose_list) -> object:
    maps = [synthetic.synthetic_maps(camera, p, SCREEN, rng=rng)[0] for p in pose_list]
    return calibrate(maps, SCREEN, "sgcc").model


@pytest.fixture(scope="module")
def fits():
    """Two sGCC fits of the mild pinhole from disjoint poses, and one of the same lens
    with k1 changed by 0.01 (a refocused or swapped lens)."""
    cam = cameras.mild_pinhole(W, H)
    rng = np.random.default_rng(8)
    ps = poses.random_poses(cam, SCREEN, 2 * POSES_PER_FIT, rng)
    changed = dataclasses.replace(cam, dist=(-0.10, *cam.dist[1:5]))
    return (_fit(cam, rng, ps[0::2]), _fit(cam, rng, ps[1::2]),
            _fit(changed, rng, ps[1::2]))


def test_sgcc_fits_of_one_camera_agree_and_of_a_changed_lens_do_not(fits, tmp_path: Path):
    a, b, wrong = fits
    sa, sb, sw = (ray_sigma_map(m, None) for m in fits)
    assert "rotation of every ray taken out" in sa.method
    same = write_diff(a, b, tmp_path / "same", names=("a", "b"), sigmas=(sa, sb))
    assert same["agree"] is True and same["uncertainty"]["a"] == sa.method
    other = write_diff(a, wrong, tmp_path / "other", names=("a", "changed"), sigmas=(sa, sw))
    assert other["agree"] is False and other["fraction_beyond_2_sigma"] > 0.5
    assert "do not agree" in (tmp_path / "other" / "diff.html").read_text()
