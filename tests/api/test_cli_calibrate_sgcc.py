"""`phasecal calibrate --observations ... --model sgcc` end to end on OpenCV's real left
sample images: the generic model fitted to detected corners, cross-validated, its figure
drawn; an OpenCV export it has no form for is one line."""

from __future__ import annotations

import json

from api.cli import main
from tests.calibration.targets.conftest import SAMPLE_SPEC, sample_images


def test_calibrate_observations_with_sgcc(tmp_path, capsys):
    images = [str(p) for p in sample_images("left")]
    assert main(["detect", "--target", SAMPLE_SPEC, "--images", *images,
                 "-o", str(tmp_path / "obs")]) == 0
    files = [str(f) for f in sorted((tmp_path / "obs").glob("*.npz"))]
    model = tmp_path / "model.json"
    assert main(["calibrate", "--observations", *files, "--model", "sgcc",
                 "--option", "target=fit", "--cross-validate", "2", "-o", str(model),
                 "--uncertainty-png", str(tmp_path / "uncertainty.png")]) == 0
    out = capsys.readouterr().out
    assert "points per cell with points; started from opencv5" in out
    assert "cross-validation (2 view sets)" in out and "-> AGREE" in out
    data = json.loads(model.read_text())
    assert data["type"] == "sgcc" and data["params"]["covariance_upper_f64_b64"]
    assert data["stats"]["cross_validation"]["verdict"] == "agree"
    assert (tmp_path / "uncertainty.png").stat().st_size > 10_000
    assert main(["calibrate", "--observations", *files, "--model", "sgcc",
                 "-o", str(tmp_path / "m2.json"),
                 "--export-opencv", str(tmp_path / "opencv.yaml")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no camera_matrix/distortion form" in err[0]
    assert err[0].endswith("m2.json is written)")
