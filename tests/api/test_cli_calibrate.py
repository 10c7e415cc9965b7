"""`phasecal calibrate / project / unproject` end to end on synthetic maps (docs/formats.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from acquisition.patterns import build_plan
from api.cli import UserError, main
from api.commands.calibrate import parse_options
from calibration.export import read_opencv_yaml
from calibration.models.base import save_model
from calibration.models.parametric import OpenCV5Model
from calibration.shared.maps import save_maps
from calibration.shared.plan import write_plan
from hw_mocks.cameras import mild_pinhole
from hw_mocks.poses import random_poses
from hw_mocks.synthetic import synthetic_maps


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    plan = build_plan(1920, 1080, 0.2745)
    write_plan(plan, d / "plan.json")
    cam = mild_pinhole()
    rng = np.random.default_rng(21)
    for i, pose in enumerate(random_poses(cam, plan.screen, 5, rng)):
        maps, _ = synthetic_maps(cam, pose, plan.screen, sigma_px=0.05, rng=rng)
        save_maps(maps, d / f"pose{i}.npz")
    return d


def test_calibrate_project_unproject(workdir, capsys) -> None:
    d = workdir
    args = ["calibrate", "--plan", str(d / "plan.json"), "--maps",
            *[str(d / f"pose{i}.npz") for i in range(5)], "--model", "opencv5",
            "-o", str(d / "model.json"), "--heldout", "4", "--max-points", "800",
            "--report", str(d / "res.png"), "--export-opencv", str(d / "cam.yaml"),
            "--export-ros", str(d / "ros.yaml")]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "held-out RMS" in out and "MODEL INADEQUATE" not in out
    doc = json.loads((d / "model.json").read_text())
    assert doc["format"] == "phasecal.model/1" and doc["type"] == "opencv5"
    assert doc["stats"]["heldout"]["per_pose"][0]["pose"] == 4
    cam = mild_pinhole()
    k, _, size = read_opencv_yaml(d / "cam.yaml")
    assert size == (640, 480) and abs(k[0, 0] / cam.fx - 1) < 2e-3
    assert "plumb_bob" in (d / "ros.yaml").read_text()
    assert (d / "res.png").stat().st_size > 0

    pix = np.array([[0.0, 0.0], [320.5, 240.25], [639.0, 479.0]])
    np.save(d / "pixels.npy", pix)
    assert main(["unproject", "--model", str(d / "model.json"), "--pixels",
                 str(d / "pixels.npy"), "-o", str(d / "rays.npz")]) == 0
    rays = np.load(d / "rays.npz")
    assert rays["origins"].shape == (3, 3) and rays["directions"].dtype == np.float64
    np.save(d / "points.npy", rays["directions"] * 750.0)
    assert main(["project", "--model", str(d / "model.json"), "--points",
                 str(d / "points.npy"), "-o", str(d / "back.npy")]) == 0
    np.testing.assert_allclose(np.load(d / "back.npy"), pix, atol=1e-6)


@pytest.mark.parametrize(
    ("model", "option"),
    [("sgcc", "cells=[6,6]"), ("sgcc", "cells=auto"), ("raygrid", "grid_step=16")],
)
def test_calibrate_generic_with_heldout_and_options(workdir, capsys, model, option) -> None:
    d = workdir
    out_json = d / f"{model}.json"
    args = ["calibrate", "--plan", str(d / "plan.json"), "--maps",
            *[str(d / f"pose{i}.npz") for i in range(5)], "--model", model,
            "-o", str(out_json), "--heldout", "4", "--option", option,
            "--report", str(d / f"{model}.png")]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "held-out RMS" in out and "MODEL INADEQUATE" not in out
    assert "ray 1-sigma: direction median" in out
    stats = json.loads(out_json.read_text())["stats"]
    assert stats["heldout"]["per_pose"][0]["pose"] == 4
    assert 0.7 < stats["noise_floor_ratio"] < 1.3
    assert 0.7 < stats["heldout"]["noise_floor_ratio"] < 1.5
    assert (d / f"{model}.png").stat().st_size > 0
    if option == "cells=auto":  # a smooth pinhole lens: the coarsest candidate suffices
        assert "mesh 10x8 chosen (validation chi2 10x8: " in out
        assert stats["cells"] == [10, 8] and len(stats["mesh_choice"]) == 3


def test_cli_errors(workdir, capsys) -> None:
    d = workdir
    base = ["calibrate", "--plan", str(d / "plan.json"), "-o", str(d / "m2.json")]
    assert main([*base, "--maps", str(d / "pose0.npz"), str(d / "nope.npz"),
                 "--model", "opencv5"]) == 1
    assert "nope.npz" in capsys.readouterr().err
    assert main([*base, "--maps", str(d / "pose0.npz"), str(d / "pose1.npz"),
                 "--model", "opencv5"]) == 1
    assert "needs >= 3" in capsys.readouterr().err
    assert main([*base, "--maps", str(d / "pose0.npz"), "--model", "pinhole9"]) == 1
    assert "--model" in capsys.readouterr().err
    maps3 = ["--maps", *[str(d / f"pose{i}.npz") for i in range(3)]]
    assert main([*base, *maps3, "--model", "sgcc", "--max-points", "500"]) == 1
    assert "--max-points: applies to the parametric models" in capsys.readouterr().err
    assert main([*base, *maps3, "--model", "sgcc", "--option", "cells"]) == 1
    assert "expected KEY=VALUE" in capsys.readouterr().err
    assert main([*base, *maps3, "--model", "sgcc", "--option", "knots=3"]) == 1
    assert "unknown key(s) ['knots']" in capsys.readouterr().err
    assert main([*base, *maps3, "--model", "sgcc", "--option", "xp=torch"]) == 1
    assert "options.xp: Input should be 'numpy' or 'cupy', got 'torch'" in capsys.readouterr().err
    assert main([*base, *maps3, "--model", "sgcc", "--option", "cells=fine"]) == 1
    assert "options.cells: expected [cu, cv] positive integers or \"auto\"" in (
        capsys.readouterr().err)
    (d / "corrupt.json").write_text('{"format": "phasecal.model/1", "type": "opencv5"}')
    np.save(d / "p.npy", np.zeros((2, 2)))
    assert main(["unproject", "--model", str(d / "corrupt.json"), "--pixels", str(d / "p.npy"),
                 "-o", str(d / "r.npz")]) == 1
    assert "image_size" in capsys.readouterr().err
    cam = mild_pinhole()
    save_model(OpenCV5Model((640, 480), cam.camera_matrix, np.asarray(cam.dist)), d / "ok.json")
    np.save(d / "bad.npy", np.zeros((4, 2)))
    assert main(["project", "--model", str(d / "ok.json"), "--points", str(d / "bad.npy"),
                 "-o", str(d / "o.npy")]) == 1
    assert "expected a numeric (N, 3)" in capsys.readouterr().err


def test_calibrate_fits_a_bowed_glazed_screen(tmp_path, capsys) -> None:
    """`--option screen="fit"` on maps of a bowed panel behind glass: the CLI stores the
    screen estimate (within 3 sigma of the hw_mocks truth) in model.json; bad values exit 1."""
    from hw_mocks.panel import PanelShape

    plan = build_plan(1920, 1080, 0.2745)
    write_plan(plan, tmp_path / "plan.json")
    cam = mild_pinhole(240, 180)
    rng = np.random.default_rng(5)
    real = PanelShape(bow_x_mm=0.5, bow_y_mm=0.3, glass_mm=1.5)
    names = []
    for i, pose in enumerate(random_poses(cam, plan.screen, 6, rng)):
        maps, _ = synthetic_maps(cam, pose, plan.screen, sigma_px=0.05, rng=rng, panel=real)
        save_maps(maps, tmp_path / f"p{i}.npz")
        names.append(str(tmp_path / f"p{i}.npz"))
    base = ["calibrate", "--plan", str(tmp_path / "plan.json"), "--maps", *names,
            "--model", "opencv5", "-o", str(tmp_path / "m.json"), "--heldout", "5"]
    assert main([*base, "--option", 'screen="fit"', "--option", "glass_index=1.52"]) == 0
    printed = capsys.readouterr().out
    assert "screen: bow_x_mm " in printed and "(glass index 1.52)" in printed
    stats = json.loads((tmp_path / "m.json").read_text())["stats"]
    scr = stats["screen"]
    assert scr["mode"] == "fit"
    for key, true in (("bow_x_mm", 0.5), ("bow_y_mm", 0.3), ("glass_mm", 1.5)):
        assert abs(scr[key] - true) < 3 * scr["std"][key]
    assert 0.8 < stats["noise_floor_ratio"] < 1.2  # flat-equivalent residuals at the noise
    assert stats["heldout"]["noise_floor_ratio"] < 1.5
    capsys.readouterr()
    assert main([*base, "--option", 'screen="curved"']) == 1
    assert "options.screen: Input should be 'flat' or 'fit', got 'curved'" in (
        capsys.readouterr().err)


def test_calibrate_fits_the_screen_inside_sgcc(tmp_path, capsys) -> None:
    """`--model sgcc-noncentral --option screen="fit"`: the joint screen estimate (within 3
    sigma of the hw_mocks truth) is printed and stored; held-out poses see the fitted screen."""
    from hw_mocks.cameras import smooth_noncentral
    from hw_mocks.panel import PanelShape

    plan = build_plan(1920, 1080, 0.2745)
    write_plan(plan, tmp_path / "plan.json")
    cam = smooth_noncentral(160, 120)
    rng = np.random.default_rng(11)
    real = PanelShape(bow_x_mm=0.5, bow_y_mm=0.3, glass_mm=1.5)
    names = []
    for i, pose in enumerate(random_poses(cam, plan.screen, 7, rng, distance_mm=(150.0, 450.0),
                                          min_coverage=0.2)):
        maps, _ = synthetic_maps(cam, pose, plan.screen, sigma_px=0.05, rng=rng, panel=real)
        save_maps(maps, tmp_path / f"p{i}.npz")
        names.append(str(tmp_path / f"p{i}.npz"))
    base = ["calibrate", "--plan", str(tmp_path / "plan.json"), "--maps", *names,
            "--model", "sgcc-noncentral", "-o", str(tmp_path / "m.json"), "--heldout", "6",
            "--option", "cells=[8,8]"]
    assert main([*base, "--option", 'screen="fit"', "--option", "glass_index=1.52"]) == 0
    printed = capsys.readouterr().out
    assert "screen: bow_x_mm " in printed and "(glass index 1.52)" in printed
    stats = json.loads((tmp_path / "m.json").read_text())["stats"]
    scr = stats["screen"]
    assert scr["mode"] == "fit" and not scr["glass_held"]
    for key, true in (("bow_x_mm", 0.5), ("bow_y_mm", 0.3), ("glass_mm", 1.5)):
        assert abs(scr[key] - true) < 3 * scr["std"][key]
    assert 0.8 < stats["noise_floor_ratio"] < 1.2
    assert stats["heldout"]["noise_floor_ratio"] < 1.5
    capsys.readouterr()
    assert main([*base, "--option", "glass_index=0.9"]) == 1
    assert "options.glass_index" in capsys.readouterr().err


def test_option_values_are_json_or_bare_strings() -> None:
    """`--option` of `calibrate` and `demo`: JSON values, a bare word as a string."""
    assert parse_options(["cells=[8,8]", "screen=fit", "central=false", "glass_index=1.52",
                          'name="a=b"']) == {"cells": [8, 8], "screen": "fit",
                                             "central": False, "glass_index": 1.52,
                                             "name": "a=b"}
    with pytest.raises(UserError, match="expected KEY=VALUE, got 'cells'"):
        parse_options(["cells"])
