"""`phasecal demo` driver on a small camera: runs the whole flow and prints the table."""

from __future__ import annotations

import io
from pathlib import Path

from api.demo import demo_rig_config, run_demo


def test_demo_small(tmp_path: Path) -> None:
    out = io.StringIO()
    rows = run_demo(tmp_path / "demo", poses=3, rig=demo_rig_config(160, 120), models=("opencv5",),
                    out=out)
    text = out.getvalue()
    assert [r.status for r in rows] == ["succeeded"], text
    row = rows[0]
    assert row.rms_px is not None and row.rms_px < 2.0
    # a 5-coefficient model on a 150-degree fisheye fits, but not to the truth's rays
    assert row.ray_median_mrad is not None and 0 < row.ray_median_mrad < 100
    assert "ray med mrad" in text and str(tmp_path / "demo" / "data") in text
    cal_dir = tmp_path / "demo" / "data" / "calibrations" / row.calibration_id
    assert (cal_dir / "model.json").is_file() and (cal_dir / "residuals.png").is_file()
    # the typed client downloaded the mrcal export (exact for the OpenCV family)
    exported = tmp_path / "demo" / "exports" / "opencv5.cameramodel"
    assert "LENSMODEL_OPENCV5" in exported.read_text()


def test_demo_on_a_rig_file_with_model_options(tmp_path: Path, capsys) -> None:
    """`phasecal demo --rig FILE --option screen="fit"`: a simulated bowed, glazed panel from
    the documented example config; the fitted screen is printed next to the table."""
    from api.cli import main as cli_main

    rig = Path(__file__).resolve().parents[2] / "docs" / "rigs" / "simulated-bowed-glass.toml"
    text = rig.read_text().replace("width = 320", "width = 160").replace("height = 240",
                                                                         "height = 120")
    small = tmp_path / "rig.toml"
    small.write_text(text)
    code = cli_main(["demo", "--rig", str(small), "--poses", "4", "--models", "opencv5",
                     "--option", 'screen="fit"', "--out", str(tmp_path / "demo")])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "screen fit: bow_x_mm" in out and "glass_mm" in out
    assert cli_main(["demo", "--rig", str(small), "--width", "100"]) == 1
    assert "camera size comes from the --rig file" in capsys.readouterr().err
    # a bad model option fails before any capture, with the field named
    assert cli_main(["demo", "--models", "opencv5", "--option", "foo=1"]) == 1
    assert "unknown key(s) ['foo'] for opencv5" in capsys.readouterr().err
