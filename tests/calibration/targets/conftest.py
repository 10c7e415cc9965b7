"""Shared inputs of the passive-target tests: OpenCV's real sample chessboard images (set up
by `make setup`, scripts/fetch-opencv-samples.sh) and simulated boards with a known bow."""

from __future__ import annotations

from pathlib import Path

import pytest

from calibration.targets.board import TargetSpec
from calibration.targets.detect import detect_file, detect_image
from hw_mocks.board import BoardRenderer, BoardTruth, look_at_poses
from hw_mocks.cameras import mild_pinhole

SAMPLES = Path(__file__).resolve().parents[3] / "data" / "opencv-samples"
SAMPLE_SPEC = "chessboard:9x6:25"  # OpenCV's stereo sample: 9x6 inner corners (square: 25 mm)
SIM_BOARD = BoardTruth(9, 6, 20.0, bow_x_mm=1.5, bow_y_mm=-0.8)


def sample_images(side: str) -> list[Path]:
    """left01..left14 (no 10) or right..., failing (not skipping) where set-up was not run."""
    files = sorted(SAMPLES.glob(f"{side}[0-9][0-9].jpg"))
    if len(files) != 13:
        pytest.fail(f"OpenCV's sample images are missing from {SAMPLES} (found {len(files)}); "
                    "run `make setup` or `bash scripts/fetch-opencv-samples.sh`")
    return files


@pytest.fixture(scope="session")
def sample_views():
    """Detected views of the left and right sample cameras: {side: [TargetObservations]}."""
    spec = TargetSpec.parse(SAMPLE_SPEC)
    out = {}
    for side in ("left", "right"):
        found = [detect_file(p, spec) for p in sample_images(side)]
        out[side] = [d.observations for d in found if d.observations is not None]
    return out


@pytest.fixture(scope="session")
def simulated():
    """Ten rendered views of a bowed board through the mild pinhole truth camera, detected:
    (camera, views, poses)."""
    cam = mild_pinhole()
    renderer = BoardRenderer(cam)
    spec = TargetSpec.parse("chessboard:9x6:20")
    poses = look_at_poses(SIM_BOARD, 10, 420.0, seed=2)
    views = []
    for k, pose in enumerate(poses):
        img = renderer.render(SIM_BOARD, pose, blur_px=1.0, seed=200 + k)
        found = detect_image(img, spec, source=f"sim{k}")
        assert found.observations is not None, found.reason
        views.append(found.observations)
    return cam, views, poses
