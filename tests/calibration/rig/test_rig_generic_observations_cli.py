"""`phasecal calibrate` of a rig with an sGCC camera from target observations, end to end:
the rig file, the camera's rays in the reference frame through `unproject --camera`, a
held-out view, and raygrid refused in one line."""

from __future__ import annotations

import json

import numpy as np

from api.cli import main
from tests.calibration.rig.conftest import SCREEN, board_view_files, two_pinholes

VIEWS = 6


def test_sgcc_camera_from_observations_through_the_cli(tmp_path, capsys) -> None:
    truth = two_pinholes()
    rng = np.random.default_rng(21)
    inputs = board_view_files(tmp_path, truth, SCREEN, VIEWS, rng)
    out = tmp_path / "rig.json"
    assert main(["calibrate", "--observations", *inputs, "--model", "opencv5",
                 "--model", "B=sgcc", "--heldout-view", f"v{VIEWS - 1}", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "intrinsics held" not in printed  # B's spline was fitted jointly
    scores = printed.split(f"held-out view v{VIEWS - 1} (pose from A): B whitened RMS ")[1]
    assert 0.5 < float(scores.split()[0]) < 2.0
    doc = json.loads(out.read_text())
    b = doc["cameras"]["B"]
    assert b["model"]["type"] == "sgcc" and "covariance_upper_f64_b64" in b["model"]["params"]
    # points in A's frame imaged by the true B, unprojected through the rig: B's rays pass
    # through them
    pts = np.array([[40.0, -20.0, 420.0], [120.0, 30.0, 500.0], [60.0, 40.0, 380.0]])
    pix = truth.cameras["B"].project(pts @ truth.rotations["B"].T + truth.translations["B"])
    np.save(tmp_path / "pix.npy", pix)
    assert main(["unproject", "--model", str(out), "--camera", "B", "--pixels",
                 str(tmp_path / "pix.npy"), "-o", str(tmp_path / "rays.npz")]) == 0
    rays = np.load(tmp_path / "rays.npz")
    miss = np.linalg.norm(np.cross(pts - rays["origins"], rays["directions"]), axis=1)
    assert miss.max() < 0.5  # mm, at 0.4-0.5 m
    capsys.readouterr()
    assert main(["calibrate", "--observations", *inputs, "--model", "opencv5",
                 "--model", "B=raygrid", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert "camera B: raygrid: a rig fits it from decoded maps only" in err
    assert err.count("\n") == 1
