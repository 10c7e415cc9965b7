"""Packaging: ranges in pyproject.toml pinned by constraints.txt, extras named with their install
command, `phasecal --version`, and a fresh venv without extras running the whole flow."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from acquisition.rig import RigConfigError, load_rig_config, open_rig
from api.cli import main
from calibration import extras

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def _name(req: str) -> str:
    return re.split(r"[<>=!~\[ ;]", req, maxsplit=1)[0].lower().replace("_", "-")


def _pins() -> dict[str, str]:
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not an exact pin"
            pins[name.lower().replace("_", "-")] = version
    return pins


def test_runtime_dependencies_are_ranges_pinned_by_constraints():
    project = PYPROJECT["project"]
    pins = _pins()
    reqs = list(project["dependencies"])
    for name, group in project["optional-dependencies"].items():
        if name != "gpu":  # CuPy needs CUDA: not part of the locked, installed-everywhere set
            reqs += [r for r in group if not r.startswith("phasecal[")]
    for req in project["dependencies"]:
        assert "==" not in req, f"{req}: a runtime dependency must be a compatible range"
    for req in reqs:
        assert _name(req) in pins, f"{req} is not pinned in constraints.txt"
    assert set(project["optional-dependencies"]) >= {"aravis", "sdl", "usb", "dask", "gpu",
                                                     "all", "dev"}
    assert set(extras.EXTRAS) <= set(project["optional-dependencies"])
    assert "license" in project and isinstance(project["license"], str)  # SPDX, no warning


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert re.match(r"phasecal \d+\.\d+", capsys.readouterr().out)


def test_a_missing_extra_names_the_install_command(monkeypatch, tmp_path):
    monkeypatch.setattr(extras, "installed", lambda extra: extra != "aravis")
    with pytest.raises(extras.MissingExtra, match=r"pip install 'phasecal\[aravis\]'"):
        extras.require("aravis")
    rig = tmp_path / "rig.toml"
    rig.write_text((ROOT / "docs" / "rigs" / "sdl-aravis.toml").read_text())
    with pytest.raises(RigConfigError, match=r"pip install 'phasecal\[aravis\]'"):
        open_rig(load_rig_config(rig))


@pytest.mark.slow
def test_fresh_venv_without_extras_runs_the_flow(tmp_path):
    """`pip install .` (constraints, no extras) runs plan/serve/decode/calibrate/export, and
    an Aravis rig asks for its extra (tests/fresh_venv_flow.py)."""
    src = tmp_path / "src"
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT,
                           capture_output=True, check=True).stdout.split(b"\0")
    for f in filter(None, files):
        dest = src / f.decode()
        dest.parent.mkdir(parents=True, exist_ok=True)
        if (ROOT / f.decode()).is_file():
            dest.write_bytes((ROOT / f.decode()).read_bytes())
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    subprocess.run([str(venv / "bin" / "pip"), "install", "-q", "-c",
                    str(src / "constraints.txt"), str(src)], check=True)
    work = tmp_path / "work"
    work.mkdir()
    # -P: the script's folder (tests/, whose test packages mirror api/ and calibration/) must
    # not shadow the installed packages.
    r = subprocess.run([str(venv / "bin" / "python"), "-P",
                        str(src / "tests" / "fresh_venv_flow.py"), str(work)],
                       capture_output=True, text=True, cwd=work, timeout=1200)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    assert "fresh venv flow: ok" in r.stdout
