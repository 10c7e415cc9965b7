"""Board descriptions and corner detection: chessboard (simulated truth, real images),
ChArUco partial views, and the reasons an image yields nothing."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.targets.board import TargetSpec, TargetSpecError
from calibration.targets.detect import detect_file, detect_image
from hw_mocks.board import true_corner_pixels
from tests.calibration.targets.conftest import SIM_BOARD


@pytest.mark.parametrize(("text", "message"), [
    ("board:9x6:25", "kind: expected 'chessboard' or 'charuco'"),
    ("chessboard:9x6", "expected chessboard:COLSxROWS:SQUARE_MM"),
    ("chessboard:9by6:25", "size: expected COLSxROWS"),
    ("chessboard:1x6:25", "expected >= 2 inner corners"),
    ("chessboard:9x6:-3", "square_mm: expected > 0"),
    ("charuco:5x7:20:25:DICT_4X4_50", "marker_mm: must be smaller than the square"),
    ("charuco:5x7:20:15:DICT_9X9_1", "dictionary: unknown"),
])
def test_bad_target_descriptions_are_named(text, message):
    with pytest.raises(TargetSpecError, match=message):
        TargetSpec.parse(text)


def test_description_round_trip_and_points():
    spec = TargetSpec.parse("charuco:5x7:20:15:dict_4x4_50")
    assert TargetSpec.parse(spec.describe()) == spec
    assert spec.points().shape == (4 * 6, 3)
    board = TargetSpec.parse("chessboard:9x6:25").points()
    assert board.shape == (54, 3) and board[1, 0] == 25.0 and board[9, 1] == 25.0


def test_simulated_corners_match_the_truth(simulated):
    cam, views, poses = simulated
    for obs, pose in zip(views, poses, strict=True):
        err = obs.image_xy - true_corner_pixels(cam, SIM_BOARD, pose)
        # numbered from the board's black end, as the renderer's truth: sub-pixel agreement
        assert np.median(np.hypot(err[:, 0], err[:, 1])) < 0.1
        assert obs.meta["detector"].endswith("cornerSubPix")
        assert np.all(obs.weight > 0)


def test_every_real_sample_image_is_detected(sample_views):
    assert [len(sample_views[s]) for s in ("left", "right")] == [13, 13]
    assert all(v.used_count() == 54 for s in sample_views.values() for v in s)


def test_charuco_partial_view():
    spec = TargetSpec.parse("charuco:7x5:30:22:DICT_5X5_100")
    flat = spec.charuco_board().generateImage((700, 500), marginSize=20)
    # a quarter of the board cut away: markers name the corners that remain
    img = np.full((480, 640), 255, np.uint8)
    img[:, :] = cv2.warpPerspective(flat, np.array([[0.9, 0.05, -150], [-0.03, 0.9, 20],
                                                    [0.0, 0.0001, 1]]), (640, 480),
                                    borderValue=255)
    found = detect_image(img, spec, source="partial")
    obs = found.observations
    assert obs is not None, found.reason
    seen = obs.used()
    assert 6 <= seen.sum() < spec.points().shape[0]
    assert np.isnan(obs.image_xy[~seen]).all()


def test_images_without_the_board_say_why(tmp_path):
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((120, 160), 128, np.uint8))
    found = detect_file(blank, TargetSpec.parse("chessboard:9x6:25"))
    assert found.observations is None and "no complete 9x6" in found.reason
    found = detect_file(tmp_path / "none.png", TargetSpec.parse("chessboard:9x6:25"))
    assert found.reason == "image file not found"
