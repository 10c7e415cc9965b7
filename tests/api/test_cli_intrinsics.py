"""`phasecal intrinsics` end to end: white flats (images, captured frames), two-rectangle
images, pan-tilt images and decoded poses, compared with hw_mocks truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from acquisition.patterns import build_plan
from api.cli import main
from calibration.fit.classic.quick import white_flat_index
from calibration.models.base import load_model
from calibration.shared.maps import save_maps
from calibration.shared.plan import write_plan
from hw_mocks.cameras import PinholeCamera
from hw_mocks.poses import random_poses, rotation_only_poses
from hw_mocks.rectangles import (
    boards_image,
    general_motion_views,
    pan_tilt_poses,
    two_board_scene,
    white_flat_image,
    whole_screen_poses,
)
from hw_mocks.rig import DEFAULT_SCREEN
from hw_mocks.synthetic import synthetic_maps

CAM = PinholeCamera(640, 480, fx=520.0, fy=530.0, cx=331.0, cy=233.5)


def _err(path) -> float:
    d = json.loads(path.read_text())
    assert d["format"] == "phasecal.intrinsics/1"
    return max(abs(d["fx"] / CAM.fx - 1), abs(d["fy"] / CAM.fy - 1),
               abs(d["cx"] - CAM.cx) / CAM.fx, abs(d["cy"] - CAM.cy) / CAM.fx)


@pytest.fixture(scope="module")
def flats(tmp_path_factory):
    d = tmp_path_factory.mktemp("flats")
    rng = np.random.default_rng(31)
    for i, pose in enumerate(whole_screen_poses(CAM, DEFAULT_SCREEN, 5, rng)):
        cv2.imwrite(str(d / f"flat{i}.png"), white_flat_image(CAM, pose, DEFAULT_SCREEN, rng))
    return d


def test_rectangle_from_white_flat_images_and_frames(flats, capsys) -> None:
    imgs = [str(flats / f"flat{i}.png") for i in range(5)]
    assert main(["intrinsics", "--method", "rectangle", "--images", *imgs,
                 "-o", str(flats / "k.json"), "--model-out", str(flats / "model.json")]) == 0
    assert _err(flats / "k.json") < 0.02
    model = load_model(flats / "model.json")
    assert model.type_name == "opencv5" and model.image_size == (640, 480)
    np.testing.assert_allclose(model.camera_matrix[0, 0],
                               json.loads((flats / "k.json").read_text())["fx"])
    assert "rectangle from 5 views: fx" in capsys.readouterr().out
    # the same white flats inside captured-pose frame stacks (docs/formats.md .npy)
    plan = build_plan(DEFAULT_SCREEN.width_px, DEFAULT_SCREEN.height_px, 0.25)
    write_plan(plan, flats / "plan.json")
    stacks = []
    for i in range(5):
        img = cv2.imread(imgs[i], cv2.IMREAD_UNCHANGED)
        stack = np.zeros((len(plan.frames), *img.shape), img.dtype)
        stack[white_flat_index(plan)] = img
        np.save(flats / f"frames{i}.npy", stack)
        stacks.append(str(flats / f"frames{i}.npy"))
    assert main(["intrinsics", "--method", "rectangle", "--frames", *stacks[:4], "--plan",
                 str(flats / "plan.json"), "-o", str(flats / "k4.json")]) == 0
    assert _err(flats / "k4.json") < 0.02


def test_selfcal_and_rotation_from_images(tmp_path) -> None:
    rng = np.random.default_rng(32)
    boards = two_board_scene()
    names = []
    for i, view in enumerate(general_motion_views(CAM, boards, 4, rng)):
        names.append(str(tmp_path / f"two{i}.png"))
        cv2.imwrite(names[-1], boards_image(CAM, boards, view, rng))
    assert main(["intrinsics", "--method", "selfcal", "--images", *names,
                 "-o", str(tmp_path / "s.json")]) == 0
    assert _err(tmp_path / "s.json") < 0.01
    pt = []
    for i, pose in enumerate(pan_tilt_poses(CAM, DEFAULT_SCREEN, 5, rng)):
        pt.append(str(tmp_path / f"pt{i}.png"))
        cv2.imwrite(pt[-1], white_flat_image(CAM, pose, DEFAULT_SCREEN, rng))
    assert main(["intrinsics", "--method", "rotation", "--images", *pt,
                 "-o", str(tmp_path / "r.json")]) == 0
    assert _err(tmp_path / "r.json") < 0.02


def test_from_decoded_maps_and_errors(tmp_path, capsys) -> None:
    rng = np.random.default_rng(33)
    plan = build_plan(1920, 1080, 0.2745)
    write_plan(plan, tmp_path / "plan.json")
    moved = random_poses(CAM, plan.screen, 5, rng)
    turned = rotation_only_poses(CAM, plan.screen, 4, rng, max_rotation_deg=20.0)
    for name, poses in (("m", moved), ("r", turned)):
        for i, pose in enumerate(poses):
            maps, _ = synthetic_maps(CAM, pose, plan.screen, sigma_px=0.05, rng=rng)
            save_maps(maps, tmp_path / f"{name}{i}.npz")
    m = [str(tmp_path / f"m{i}.npz") for i in range(5)]
    r = [str(tmp_path / f"r{i}.npz") for i in range(4)]
    common = ["--plan", str(tmp_path / "plan.json"), "-o", str(tmp_path / "k.json")]
    assert main(["intrinsics", "--method", "rectangle", "--maps", *m, *common]) == 0
    assert _err(tmp_path / "k.json") < 0.005
    d = json.loads((tmp_path / "k.json").read_text())  # std from redrawn decoded points
    assert 0 < d["std"]["fx"] and abs(d["fx"] - CAM.fx) < 5 * d["std"]["fx"] + 0.01
    assert main(["intrinsics", "--method", "rotation", "--maps", *r, *common]) == 0
    assert _err(tmp_path / "k.json") < 0.01
    capsys.readouterr()
    assert main(["intrinsics", "--method", "selfcal", "--maps", *m, *common]) == 1
    assert "two non-parallel rectangles" in capsys.readouterr().err
    assert main(["intrinsics", "--method", "rectangle", "--maps", *m[:3], *common]) == 1
    assert ">= 4 views" in capsys.readouterr().err
    assert main(["intrinsics", "--method", "rectangle", "--maps", *m,
                 "-o", str(tmp_path / "k.json")]) == 1
    assert "--plan: required" in capsys.readouterr().err
