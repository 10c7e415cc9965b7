"""`phasecal detect` then `phasecal calibrate --observations` end to end on OpenCV's real
sample images (set up by `make setup`)."""

from __future__ import annotations

import json

import pytest

from api.cli import main
from calibration.shared.observations import load_observations
from tests.calibration.targets.conftest import SAMPLE_SPEC, sample_images


@pytest.fixture(scope="module")
def detected(tmp_path_factory):
    out = tmp_path_factory.mktemp("detect")
    images = [str(p) for p in sample_images("right")]
    assert main(["detect", "--target", SAMPLE_SPEC, "--images", *images, "--camera", "right",
                 "-o", str(out / "obs")]) == 0
    return out


def test_detect_writes_one_view_per_image(detected, capsys):
    files = sorted((detected / "obs").glob("*.npz"))
    assert [f.stem for f in files] == [p.stem for p in sample_images("right")]
    obs = load_observations(files[0])
    assert obs.used_count() == 54 and obs.image_size == (640, 480)
    assert obs.meta["camera"] == "right" and obs.meta["target"] == SAMPLE_SPEC


def test_an_image_without_the_board_gets_one_line(detected, tmp_path, capsys):
    bogus = tmp_path / "notes.png"
    bogus.write_text("not an image")
    good = str(sample_images("left")[0])
    assert main(["detect", "--target", SAMPLE_SPEC, "--images", good, str(bogus),
                 "-o", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"{bogus}: nothing detected: not an image OpenCV can read"]
    assert main(["detect", "--target", SAMPLE_SPEC, "--images", str(bogus),
                 "-o", str(tmp_path / "o2")]) == 1
    assert "no image showed the target" in capsys.readouterr().err
    assert main(["detect", "--target", "chessboard:9x6", "--images", good,
                 "-o", str(tmp_path / "o3")]) == 1
    assert "--target: target 'chessboard:9x6': expected" in capsys.readouterr().err


def test_calibrate_observations_with_cross_validation(detected, capsys):
    files = [str(f) for f in sorted((detected / "obs").glob("*.npz"))]
    model = detected / "model.json"
    assert main(["calibrate", "--observations", *files, "--model", "opencv5",
                 "--option", "target=fit", "--cross-validate", "2", "-o", str(model),
                 "--report", str(detected / "residuals.png"),
                 "--uncertainty-png", str(detected / "uncertainty.png")]) == 0
    out = capsys.readouterr().out
    assert "target bow: x" in out and "cross-validation (2 view sets)" in out
    data = json.loads(model.read_text())
    assert data["type"] == "opencv5"
    assert data["stats"]["cross_validation"]["verdict"] == "agree"
    assert (detected / "residuals.png").stat().st_size > 10_000
    assert (detected / "uncertainty.png").stat().st_size > 10_000
    # bad inputs: one line, exit 1
    for argv, message in [
        (["--model", "raygrid"], "raygrid cannot be fitted to target observations"),
        (["--model", "opencv5", "--option", "target=bent"], "options.target"),
        (["--model", "opencv5", "--cross-validate", "1"], "--cross-validate: expected >= 2"),
        (["--model", "opencv5", "--heldout", "1"], "--heldout: not for --observations"),
    ]:
        assert main(["calibrate", "--observations", *files, "-o", str(detected / "x.json"),
                     *argv]) == 1
        assert message in capsys.readouterr().err
    assert main(["calibrate", "--observations", *files, "--maps", files[0], "--model",
                 "opencv5", "-o", str(detected / "x.json")]) == 1
    assert "--maps and --observations together" in capsys.readouterr().err
    assert not (detected / "x.json").exists()
