"""`phasecal capture` on a rig of several simulated cameras: every camera captured in sync
into its own folder of the pose and decoded, each camera's maps checked against that
camera's truth (from outside the product); a folder of other cameras is refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from api.cli import main as cli_main
from calibration.shared.maps import load_maps
from hw_mocks.truth import SimulatorTruth

SCREEN = {"width_px": 320, "height_px": 240, "pitch_mm": [0.5, 0.5]}
CONFIG = {"kind": "simulated", "screen": SCREEN, "cameras": [
    {"name": "left", "model": "mild_pinhole", "width": 80, "height": 60},
    {"name": "right", "model": "mild_pinhole", "width": 96, "height": 72,
     "trigger_latency_s": 1e-3},
]}


@pytest.fixture(scope="module")
def captured(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """A plan, the two-camera rig's config file and one pose captured by the CLI."""
    tmp = tmp_path_factory.mktemp("cli-rig")
    plan, rig, pose = tmp / "plan.json", tmp / "two.json", tmp / "pose"
    rig.write_text(json.dumps(CONFIG))
    assert cli_main(["plan", "--screen-width-px", "320", "--screen-height-px", "240",
                     "--pitch-mm", "0.5", "--preset", "fast", "-o", str(plan)]) == 0
    assert cli_main(["capture", "--rig", str(rig), "--plan", str(plan), "-o", str(pose)]) == 0
    return plan, rig, pose


def test_each_camera_gets_its_own_maps_matching_its_truth(captured, capsys) -> None:
    plan, rig, pose = captured
    truth = SimulatorTruth.from_config(CONFIG)
    assert json.loads((pose / "cameras.json").read_text()) == ["left", "right"]
    assert not (pose / "maps.npz").exists()  # no reference-only maps beside the cameras'
    for cam in CONFIG["cameras"]:
        folder = pose / "cameras" / cam["name"]
        maps = load_maps(folder / "maps.npz")
        assert maps.shape == (cam["height"], cam["width"])
        assert maps.meta["camera_name"] == cam["name"]
        summary = json.loads((folder / "decode.json").read_text())
        assert summary == {"valid_pixels": maps.valid_count(), "width": cam["width"],
                           "height": cam["height"]}
        x_true, _ = truth.screen_points(None, cam["name"])
        assert maps.mask.sum() > 0.5 * np.isfinite(x_true).sum(), cam["name"]
        assert np.median(np.abs((maps.x - x_true)[maps.mask])) < 0.2  # screen px
        errors = truth.normalized_errors(maps, None, cam["name"])
        assert 0.5 < np.std(errors) < 2.0, cam["name"]  # its own truth, not the other's
    # a second run finds every camera's frames stored and decodes them again
    capsys.readouterr()
    assert cli_main(["capture", "--rig", str(rig), "--plan", str(plan), "-o", str(pose)]) == 0
    out = capsys.readouterr().out
    assert "captured 0, resumed from" in out
    assert "cameras/left/maps.npz" in out and "cameras/right/maps.npz" in out


def test_a_pose_folder_of_other_cameras_is_refused(captured, tmp_path: Path, capsys) -> None:
    plan, _, pose = captured
    other = tmp_path / "three.json"
    other.write_text(json.dumps({**CONFIG, "cameras": [
        *CONFIG["cameras"], {"name": "top", "width": 64, "height": 48}]}))
    assert cli_main(["capture", "--rig", str(other), "--plan", str(plan), "-o",
                     str(pose)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "captured with cameras ['left', 'right']" in err[0]
    assert "the rig has cameras ['left', 'right', 'top']" in err[0]
