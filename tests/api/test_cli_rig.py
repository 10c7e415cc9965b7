"""`phasecal calibrate` of a rig (CAMERA/VIEW= inputs), `project`/`unproject --camera` in the
reference frame and the rig exports, end to end on simulated two-camera maps."""

from __future__ import annotations

import json
import subprocess

import cv2
import numpy as np
import pytest

from acquisition.patterns import build_plan
from api.cli import main
from calibration.mrcal_io import read_cameramodel_with_extrinsics
from calibration.shared.plan import write_plan
from tests.calibration.rig.conftest import board_view_files, maps_view_files, two_pinholes
from tests.calibration.test_exports import SYSTEM_PYTHON, needs_mrcal

VIEWS = 5


@pytest.fixture(scope="module")
def rig_dir(tmp_path_factory):
    """Maps of two cameras in 5 shared views, and the rig fitted from them by the CLI."""
    d = tmp_path_factory.mktemp("rig")
    plan = build_plan(640, 400, 0.5)
    write_plan(plan, d / "plan.json")
    truth = two_pinholes()
    inputs = maps_view_files(d, truth, plan.screen, VIEWS, np.random.default_rng(8))
    assert main(["calibrate", "--plan", str(d / "plan.json"), "--maps", *inputs,
                 "--model", "opencv5", "--model", "B=opencv-rational",
                 "--option", "max_points_per_view=400", "-o", str(d / "rig.json")]) == 0
    return d, truth


def test_rig_file_and_project_unproject_in_the_reference_frame(rig_dir, capsys) -> None:
    d, truth = rig_dir
    doc = json.loads((d / "rig.json").read_text())
    assert doc["format"] == "phasecal.rig/1" and doc["reference"] == "A"
    assert doc["cameras"]["B"]["model"]["type"] == "opencv-rational"
    assert np.array(doc["cameras"]["B"]["extrinsics"]["covariance"]).shape == (6, 6)
    # points in A's frame, projected into B, unprojected back: B's rays pass through them
    pts = np.array([[40.0, -20.0, 420.0], [120.0, 30.0, 500.0]])
    np.save(d / "pts.npy", pts)
    assert main(["project", "--model", str(d / "rig.json"), "--camera", "B", "--points",
                 str(d / "pts.npy"), "-o", str(d / "pix.npy")]) == 0
    pix = np.load(d / "pix.npy")
    r_true, t_true = truth.rotations["B"], truth.translations["B"]
    expect = truth.cameras["B"].project(pts @ r_true.T + t_true)
    assert np.allclose(pix, expect, atol=0.5)  # the fitted rig against the simulated truth
    assert main(["unproject", "--model", str(d / "rig.json"), "--camera", "B", "--pixels",
                 str(d / "pix.npy"), "-o", str(d / "rays.npz")]) == 0
    rays = np.load(d / "rays.npz")
    miss = np.cross(pts - rays["origins"], rays["directions"])
    assert np.linalg.norm(miss, axis=1).max() < 1e-6
    assert np.linalg.norm(rays["origins"][0] - (-r_true.T @ t_true)) < 1.0  # B's centre in A
    capsys.readouterr()
    assert main(["project", "--model", str(d / "rig.json"), "--points", str(d / "pts.npy"),
                 "-o", str(d / "x.npy")]) == 1
    assert "is a rig; name one of ['A', 'B']" in capsys.readouterr().err


def test_opencv_stereo_is_read_by_filestorage_and_rectifies(rig_dir, tmp_path) -> None:
    d, truth = rig_dir
    out = tmp_path / "stereo.yaml"
    assert main(["export", "--model", str(d / "rig.json"), "--cameras", "A,B", "--format",
                 "opencv-stereo", "-o", str(out)]) == 0
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    k1, d1, k2, d2, r, t, e, f = (fs.getNode(n).mat() for n in "K1 D1 K2 D2 R T E F".split())
    size = tuple(int(v) for v in fs.getNode("image_size_1").mat().ravel())
    fs.release()
    r_true, t_true = truth.relative("A", "B")
    assert np.linalg.norm(cv2.Rodrigues(r @ r_true.T)[0]) < 2e-3
    assert np.linalg.norm(t.ravel() - t_true) < 1.0 and d2.size == 12
    tx = np.array([[0, -t[2, 0], t[1, 0]], [t[2, 0], 0, -t[0, 0]], [-t[1, 0], t[0, 0], 0]])
    assert np.allclose(e, tx @ r)
    r1, r2, p1, p2, *_ = cv2.stereoRectify(k1, d1, k2, d2, size, r, t)
    # rectified: a point seen by both cameras lands on the same image row
    x = np.array([[30.0, 10.0, 450.0]])
    uv1 = cv2.projectPoints(x, np.zeros(3), np.zeros(3), k1, d1)[0]
    uv2 = cv2.projectPoints(x, cv2.Rodrigues(r)[0], t, k2, d2)[0]
    y1 = cv2.undistortPoints(uv1, k1, d1, R=r1, P=p1)[0, 0, 1]
    y2 = cv2.undistortPoints(uv2, k2, d2, R=r2, P=p2)[0, 0, 1]
    assert abs(y1 - y2) < 1e-6
    # x2^T F x1 = 0 on the distortion-free pixels
    h1 = np.array([*cv2.undistortPoints(uv1, k1, d1, P=k1)[0, 0], 1.0])
    h2 = np.array([*cv2.undistortPoints(uv2, k2, d2, P=k2)[0, 0], 1.0])
    assert abs(h2 @ f @ h1) < 1e-6


def test_stereo_remap_and_mrcal_extrinsics_round_trip(rig_dir, tmp_path) -> None:
    d, _ = rig_dir
    rig = json.loads((d / "rig.json").read_text())
    assert main(["export", "--model", str(d / "rig.json"), "--camera", "B", "--format", "mrcal",
                 "-o", str(tmp_path / "b.cameramodel")]) == 0
    model, rt = read_cameramodel_with_extrinsics(tmp_path / "b.cameramodel")
    ext = rig["cameras"]["B"]["extrinsics"]
    assert np.allclose(cv2.Rodrigues(rt[:3])[0], ext["R"], atol=1e-12)
    assert np.allclose(rt[3:], ext["t_mm"]) and model.type_name == "opencv-rational"
    assert main(["export", "--model", str(d / "rig.json"), "--cameras", "A,B", "--format",
                 "stereo-remap", "-o", str(tmp_path / "rect.npz")]) == 0
    with np.load(tmp_path / "rect.npz") as z:
        assert z["map1_x"].shape == (240, 320) and z["map2_y"].dtype == np.float32
        assert json.loads(str(z["meta"]))["method"] == "opencv"


def test_bad_rig_inputs_are_one_line_errors(rig_dir, capsys) -> None:
    d, _ = rig_dir
    base = ["calibrate", "--plan", str(d / "plan.json"), "-o", str(d / "x.json")]
    a0 = f"A/v0={d / 'A0.npz'}"
    cases = [
        ([*base, "--maps", a0, str(d / "B0.npz"), "--model", "opencv5"], "either every file"),
        ([*base, "--maps", a0, f"B/v0={d / 'B0.npz'}", "--model", "C=opencv5"],
         "no inputs for camera(s) ['C']"),
        ([*base, "--maps", *[f"A/v{k}={d / f'A{k}.npz'}" for k in range(3)],
          *[f"B/w{k}={d / f'B{k}.npz'}" for k in range(3)], "--model", "opencv5"],
         "groups: A | B"),
    ]
    for argv, message in cases:
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert main(["export", "--model", str(d / "rig.json"), "--format", "ros", "-o",
                 str(d / "r.yaml")]) == 1
    assert "name one (--camera)" in capsys.readouterr().err


def test_rig_from_target_observations_needs_no_plan(tmp_path, capsys) -> None:
    truth = two_pinholes()
    rng = np.random.default_rng(4)
    screen = build_plan(640, 400, 0.5).screen
    inputs = board_view_files(tmp_path, truth, screen, 4, rng, grid=(9, 6))
    out = tmp_path / "rig.json"
    assert main(["calibrate", "--observations", *inputs, "--model", "opencv5",
                 "--heldout-view", "v3", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "held-out view v3 (pose from A): B whitened RMS" in printed
    assert json.loads(out.read_text())["cameras"]["B"]["model"]["type"] == "opencv5"
    assert main(["calibrate", "--observations", *inputs, "--model", "opencv5",
                 "--max-points", "100", "-o", str(out)]) == 1
    assert "max_points_per_view" in capsys.readouterr().err


@needs_mrcal
def test_mrcal_reads_the_rig_cameras_extrinsics(rig_dir, tmp_path) -> None:
    """mrcal itself (the system python3-mrcal) maps a reference-frame point into camera B as
    the rig model does."""
    d, _ = rig_dir
    path = tmp_path / "b.cameramodel"
    assert main(["export", "--model", str(d / "rig.json"), "--camera", "B", "--format", "mrcal",
                 "-o", str(path)]) == 0
    p = np.array([25.0, -12.0, 480.0])
    script = ("import mrcal, numpy as np, sys\n"
              "m = mrcal.cameramodel(sys.argv[1])\n"
              "print(*mrcal.transform_point_rt(m.extrinsics_rt_fromref(), "
              "np.array([float(v) for v in sys.argv[2:]])))\n")
    out = subprocess.run([SYSTEM_PYTHON, "-c", script, str(path), *map(str, p)],
                         capture_output=True, text=True, check=True).stdout
    ext = json.loads((d / "rig.json").read_text())["cameras"]["B"]["extrinsics"]
    expect = np.asarray(ext["R"]) @ p + np.asarray(ext["t_mm"])
    assert np.allclose([float(v) for v in out.split()], expect, atol=1e-9)
