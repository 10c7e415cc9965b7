"""`phasecal report` of a rig model, end to end on simulated two-camera maps and board
observations: the page the service draws (every camera, the extrinsics with their 1-sigma
from the rig file, the held-out view's score), its downloads beside it, the self-contained
copy, the statistics the rig model carries when the fit's result is not at hand, and a
one-line error for inputs that do not fit the model."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from acquisition.patterns import build_plan
from api.cli import main
from calibration.shared.plan import write_plan
from tests.api.rig_report_checks import check_extrinsics_row, table_rows
from tests.calibration.rig.conftest import (
    SCREEN,
    board_view_files,
    maps_view_files,
    two_pinholes,
)

VIEWS = 5
HELD = f"v{VIEWS - 1}"


@pytest.fixture(scope="module")
def maps_rig(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[str]]:
    """Two cameras' maps of 5 shared views and the rig `phasecal calibrate` fitted from
    them (the last view held out): (folder, the CAMERA/VIEW=PATH inputs)."""
    d = tmp_path_factory.mktemp("rig-report")
    plan = build_plan(640, 400, 0.5)
    write_plan(plan, d / "plan.json")
    truth = two_pinholes()
    inputs = maps_view_files(d, truth, plan.screen, VIEWS, np.random.default_rng(8))
    assert main(["calibrate", "--plan", str(d / "plan.json"), "--maps", *inputs,
                 "--model", "opencv5", "--heldout-view", HELD,
                 "--option", "max_points_per_view=400", "-o", str(d / "rig.json")]) == 0
    return d, inputs


def test_rig_report_names_every_camera_and_the_extrinsics_with_sigma(maps_rig, tmp_path,
                                                                     capsys) -> None:
    d, inputs = maps_rig
    assert (d / "rig.result.json").is_file()  # calibrate keeps the fit's statistics
    out = tmp_path / "report"
    capsys.readouterr()
    assert main(["report", "--model", str(d / "rig.json"), "--maps", *inputs,
                 "--heldout-view", HELD, "-o", str(out)]) == 0
    assert f"statistics from {d / 'rig.result.json'}" in capsys.readouterr().out
    page = (out / "report.html").read_text()
    assert "<meta name='phasecal-report' content='phasecal.rig-report/1'>" in page
    cams = table_rows(page, "cameras")
    assert [r[0] for r in cams] == ["A", "B"]
    assert all(r[1] == "opencv5" and r[2] == "320 x 240" and r[7] == str(VIEWS - 1)
               for r in cams)
    doc = json.loads((d / "rig.json").read_text())
    ext = doc["cameras"]["B"]["extrinsics"]
    check_extrinsics_row(page, "B", ext)
    held = re.search(r"<h2>Held-out views</h2>(.*?)<h2>", page, re.S).group(1)
    assert f"<td>{HELD}</td>" in held and "<td>B</td>" in held
    assert f"<th>held-out views</th><td>1: {HELD}</td>" in page
    # downloads are files beside the page, linked by name
    links = re.findall(r'class="download" href="([^"]+)"', page)
    assert "rig.json" in links and "A_B_stereo.yaml" in links and "B_opencv.yaml" in links
    assert all((out / h).is_file() for h in links)
    assert json.loads((out / "rig.json").read_text()) == doc
    assert sorted(p.name for p in out.glob("coverage_*.png")) == ["coverage_00.png",
                                                                  "coverage_01.png"]
    single = (out / "report-single.html").read_text()
    assert single.count('src="data:image/png;base64,') == 2 and 'href="rig.json"' not in single


def test_without_the_fit_result_the_rig_model_statistics_are_drawn(maps_rig, tmp_path) -> None:
    d, inputs = maps_rig
    moved = tmp_path / "rig.json"
    shutil.copy(d / "rig.json", moved)  # no rig.result.json beside this copy
    training = [i for i in inputs if f"/{HELD}=" not in i]
    assert main(["report", "--model", str(moved), "--maps", *training,
                 "-o", str(tmp_path / "bare")]) == 0
    assert main(["report", "--model", str(d / "rig.json"), "--maps", *inputs,
                 "--heldout-view", HELD, "-o", str(tmp_path / "full")]) == 0
    bare = (tmp_path / "bare" / "report.html").read_text()
    full = (tmp_path / "full" / "report.html").read_text()
    # the per-camera residuals and extrinsics are the same numbers, from the rig file alone
    assert table_rows(bare, "cameras") == table_rows(full, "cameras")
    assert table_rows(bare, "extrinsics") == table_rows(full, "extrinsics")
    assert "No view was held out." in bare


def test_rig_report_from_board_observations(tmp_path) -> None:
    inputs = board_view_files(tmp_path, two_pinholes(), SCREEN, 4, np.random.default_rng(21))
    rig = tmp_path / "rig.json"
    assert main(["calibrate", "--observations", *inputs, "--model", "opencv5",
                 "-o", str(rig)]) == 0
    assert main(["report", "--model", str(rig), "--observations", *inputs,
                 "-o", str(tmp_path / "report")]) == 0
    page = (tmp_path / "report" / "report.html").read_text()
    assert [r[0] for r in table_rows(page, "cameras")] == ["A", "B"]
    # coverage counted from the detected points, as the service's target-rig report does
    assert "how many training views detected a board point near each pixel" in page
    assert len(list((tmp_path / "report").glob("coverage_*.png"))) == 2


def test_inputs_that_do_not_fit_the_model_are_refused_in_one_line(maps_rig, tmp_path,
                                                                  capsys) -> None:
    d, inputs = maps_rig
    rig = str(d / "rig.json")
    single = tmp_path / "a.json"
    single.write_text(json.dumps(json.loads(Path(rig).read_text())["cameras"]["A"]["model"]))
    plain = [i.split("=", 1)[1] for i in inputs]
    stale = tmp_path / "stale.json"
    stats = json.loads((d / "rig.result.json").read_text())
    stats["stats"]["reduced_chi2"] *= 2
    stale.write_text(json.dumps(stats))
    bare = json.loads(Path(rig).read_text())  # a rig model whose cameras keep no residuals
    for cam in bare["cameras"].values():
        cam["model"]["stats"] = {}
    (tmp_path / "bare.json").write_text(json.dumps(bare))
    cases = {
        "is a rig (phasecal.rig/1); name each file CAMERA/VIEW=PATH":
            ["--model", rig, "--maps", *plain],
        "camera 'C' is not in the rig": ["--model", rig, "--maps", *inputs,
                                         f"C/v0={plain[0]}", "--heldout-view", HELD],
        "no CAMERA/VIEW= files for camera(s) ['B']":
            ["--model", rig, "--maps", *[i for i in inputs if i.startswith("A/")],
             "--heldout-view", HELD],
        "is a single-camera model; CAMERA/VIEW= prefixes are for a rig model":
            ["--model", str(single), "--plan", str(d / "plan.json"), "--maps", *inputs],
        f"the fit held out view '{HELD}'; name it with --heldout-view {HELD}":
            ["--model", rig, "--maps", *inputs],
        "--heldout-view: the fit used view 'v0'":
            ["--model", rig, "--maps", *inputs, "--heldout-view", HELD, "--heldout-view", "v0"],
        "the fit's statistics name no fitted view": [
            "--model", str(tmp_path / "bare.json"), "--maps", *inputs],
        "is not the fit of": ["--model", rig, "--maps", *inputs, "--heldout-view", HELD,
                              "--result", str(stale)],
    }
    for message, args in cases.items():
        capsys.readouterr()
        assert main(["report", *args, "-o", str(tmp_path / "never")]) == 1, message
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "never").exists()
    assert main(["calibrate", "--plan", str(d / "plan.json"), "--maps", *inputs,
                 "--model", "opencv5", "--report", str(tmp_path / "r.png"),
                 "-o", str(tmp_path / "r.json")]) == 1
    assert "use `phasecal report --model RIG`" in capsys.readouterr().err
