"""`phasecal demo` driver on a small camera: runs the whole flow and prints the table."""

from __future__ import annotations

import io
from pathlib import Path

from api.demo import run_demo


def test_demo_small(tmp_path: Path) -> None:
    out = io.StringIO()
    rows = run_demo(tmp_path / "demo", poses=3, width=160, height=120, models=("opencv5",),
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
