"""The report's verdict on made-up report data: each check reads what it claims to read.

Coverage, parameter uncertainty and duplicate poses are decided from plain inputs here, so a
check that reads the wrong field or the wrong threshold fails.
"""

from __future__ import annotations

import cv2
import numpy as np

from calibration.models.parametric import OpenCV5Model
from calibration.report_data import PoseView, ReportData
from calibration.report_verdict import (
    FAIL,
    PASS,
    WARN,
    assess,
    duplicate_poses,
    empty_regions,
    loose_parameters,
    sensor_part,
)
from calibration.shared.plan import ScreenGeometry

W, H = 160, 120


def _view(label: str, rvec: tuple[float, float, float], t: tuple[float, float, float],
          ratio: float = 1.0) -> PoseView:
    stats = {"rms_px": ratio * 0.1, "expected_rms_px": 0.1, "noise_floor_ratio": ratio,
             "n_points": 10, "outlier_fraction": 0.0}
    return PoseView(label, False, cv2.Rodrigues(np.array(rvec, float))[0], np.array(t, float),
                    np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2, 2)),
                    np.zeros(0, bool), stats)


def _data(masks: list[np.ndarray], views: list[PoseView], stats: dict) -> ReportData:
    model = OpenCV5Model((W, H), np.array([[150.0, 0, 80], [0, 150, 60], [0, 0, 1]]),
                         np.array([-0.1, 0.04, 0.0, 0.0, 0.002]))
    return ReportData(model, stats, views, masks, np.zeros((1, 2)), (1, 1), np.ones(1), "test",
                      ScreenGeometry(64, 48, (1.0, 1.0)), [])


def _left_half() -> np.ndarray:
    mask = np.zeros((H, W), bool)
    mask[:, : W // 2] = True
    return mask


def test_sensor_parts_are_named_by_ninths() -> None:
    assert sensor_part(5, 5, W, H) == "top-left corner"
    assert sensor_part(80, 60, W, H) == "centre"
    assert sensor_part(155, 60, W, H) == "right edge"
    assert sensor_part(80, 115, W, H) == "bottom edge"


def test_empty_cells_are_counted_and_placed_in_words() -> None:
    views = [_view("a", (0, 0, 0), (0, 0, 300)), _view("b", (0.3, 0, 0), (20, 0, 300))]
    data = _data([_left_half(), _left_half()], views,
                 {"noise_floor_ratio": 1.1, "param_std": {}})
    regions, empty, cells = empty_regions(data)
    assert (empty, cells) == (16 * 12 // 2, 16 * 12)  # the right half of the 16 x 12 cells
    assert {p for p, _ in regions} == {"top-right corner", "right edge", "bottom-right corner",
                                       "top edge", "centre", "bottom edge"}
    verdict = assess(data)
    coverage = next(c for c in verdict.checks if c.name == "coverage")
    assert coverage.status == FAIL and "96 of 192 cells empty" in coverage.measured
    assert "right edge" in coverage.advice and "tilted" in coverage.advice
    full = _data([np.ones((H, W), bool)] * 2, views, {"noise_floor_ratio": 1.1})
    assert next(c for c in assess(full).checks if c.name == "coverage").status == PASS


def test_parameters_with_a_wide_sigma_are_flagged() -> None:
    views = [_view("a", (0, 0, 0), (0, 0, 300))]
    std = {"fx": 0.5, "fy": 0.5, "cx": 0.2, "cy": 0.2, "k1": 0.01, "k2": 0.03, "p1": 0.0,
           "p2": 0.0, "k3": 0.5}
    data = _data([np.ones((H, W), bool)], views, {"noise_floor_ratio": 1.0, "param_std": std})
    # k2: 0.03 > 50% of 0.04, k3: 0.5 > 50% of 0.002: flagged; k1: 0.01 < 50% of 0.1: not;
    # p1, p2 have no sigma (held fixed): not parameters of the fit.
    assert [name for name, _, _ in loose_parameters(data)] == ["k2", "k3"]
    check = next(c for c in assess(data).checks if c.name == "parameter uncertainty")
    assert check.status == WARN and "2 of 7" in check.measured  # p1, p2 fixed
    assert "over-parameterised" in check.advice


def test_duplicate_poses_and_the_overall_status() -> None:
    views = [_view("a", (0, 0, 0), (0, 0, 300)), _view("b", (0.01, 0, 0), (1, 0, 300)),
             _view("c", (0.3, 0, 0), (0, 0, 300))]
    data = _data([np.ones((H, W), bool)] * 3, views,
                 {"noise_floor_ratio": 1.2, "heldout": {"noise_floor_ratio": 4.0}})
    dups = duplicate_poses(data)
    assert [(a, b) for a, b, _, _ in dups] == [("a", "b")]
    verdict = assess(data)
    status = {c.name: c.status for c in verdict.checks}
    assert status["noise-floor ratio (training poses)"] == PASS
    assert status["noise-floor ratio (held-out poses)"] == FAIL
    assert status["duplicate poses"] == WARN
    assert verdict.status == FAIL
