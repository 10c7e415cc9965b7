"""The model difference page: numbers and verdict against the combined uncertainty.

Two OpenCV models that differ by a known focal length change are compared with ray-sigma
maps of a known size: the verdict must follow the fraction of pixels beyond 2 sigma, and the
numbers in the page must be those of diff.json.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from calibration.models.parametric import OpenCV5Model
from calibration.report_diff import RaySigmaMap, summarize_difference, write_diff

W, H = 160, 120


def _model(f: float) -> OpenCV5Model:
    return OpenCV5Model((W, H), np.array([[f, 0, 80.0], [0, f, 60.0], [0, 0, 1]]),
                        np.array([-0.1, 0.04, 0.0, 0.0, 0.0]))


def _flat(sigma_rad: float) -> RaySigmaMap:
    return RaySigmaMap((6, 8), np.full(48, sigma_rad), "constant, for the test")


def test_fraction_beyond_two_sigma_decides_the_verdict() -> None:
    angle = np.array([1.0, 1.0, 1.0, 5.0, np.nan]) * 1e-6
    s = summarize_difference(angle, np.full(5, 1e-6))
    assert s["fraction_beyond_2_sigma"] == 0.25 and s["agree"] is False
    assert s["median_urad"] == 1.0 and s["max_urad"] == 5.0 and s["pixels_compared"] == 4
    assert summarize_difference(angle, np.full(5, 3e-6))["agree"] is True
    assert summarize_difference(angle, None)["agree"] is None


def test_page_of_two_models_that_differ_and_two_that_agree(tmp_path: Path) -> None:
    a, b = _model(150.0), _model(150.3)  # 0.2% focal length: up to ~1000 urad at the edges
    far = write_diff(a, b, tmp_path / "far", step_px=8.0, names=("A", "B"),
                     sigmas=(_flat(20e-6), _flat(20e-6)))
    assert far["agree"] is False and far["fraction_beyond_2_sigma"] > 0.5
    page = (tmp_path / "far" / "diff.html").read_text()
    assert "do not agree" in page and f"<td>{far['median_urad']:.4g}</td>" in page
    assert json.loads((tmp_path / "far" / "diff.json").read_text())["agree"] is False
    assert (tmp_path / "far" / "diff_sigma.png").is_file()
    assert sorted(re.findall(r'src="([^"]+)"', page)) == ["diff.png", "diff_sigma.png"]

    near = write_diff(a, b, tmp_path / "near", step_px=8.0, names=("A", "B"),
                      sigmas=(_flat(2e-3), _flat(2e-3)))
    assert near["agree"] is True and near["max_urad"] == far["max_urad"]
    assert "agree within their uncertainty" in (tmp_path / "near" / "diff.html").read_text()

    unknown = write_diff(a, b, tmp_path / "unknown", step_px=8.0, names=("A", "B"))
    assert unknown["agree"] is None and not (tmp_path / "unknown" / "diff_sigma.png").exists()
    assert "cannot be judged" in (tmp_path / "unknown" / "diff.html").read_text()

