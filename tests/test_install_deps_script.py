"""install-system-deps.sh waits for the dpkg lock (another apt at boot) instead of failing."""

from __future__ import annotations

import os
import stat
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "install-system-deps.sh"


def _fake(bin_dir: Path, name: str, body: str) -> None:
    p = bin_dir / name
    p.write_text("#!/bin/sh\n" + body)
    p.chmod(p.stat().st_mode | stat.S_IXUSR)


@pytest.mark.skipif(os.geteuid() != 0, reason="the script installs only as root")
def test_every_apt_call_waits_for_the_lock(tmp_path: Path) -> None:
    log = tmp_path / "apt.log"
    _fake(tmp_path, "dpkg-query", "exit 1\n")  # every package missing
    _fake(tmp_path, "apt-get", f'echo "$*" >> {log}\n')
    env = dict(os.environ, PATH=f"{tmp_path}:{os.environ['PATH']}")
    subprocess.run(["bash", str(SCRIPT)], check=True, env=env, capture_output=True, timeout=60)
    calls = log.read_text().splitlines()
    assert any(" update" in c for c in calls) and any(" install " in c for c in calls)
    assert all("DPkg::Lock::Timeout=600" in c for c in calls), calls
