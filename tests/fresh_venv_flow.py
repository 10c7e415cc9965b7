"""Run by tests/test_packaging.py with a fresh venv's Python (phasecal installed without any
extra): plan, serve on the simulated rig, capture, decode, calibrate, export, and an Aravis
rig asking for its extra. Prints one line per step; exits non-zero on the first failure."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import cv2
import numpy as np

from api.client import PhasecalClient
from api.demo import demo_rig_config
from api.inprocess import free_port
from calibration.shared.plan import ScreenGeometry
from hw_mocks.cameras import mild_pinhole
from hw_mocks.poses import random_poses

BIN = Path(sys.executable).parent
SCREEN = ScreenGeometry(320, 240, (0.5, 0.5))
ARAVIS_RIG = """format = "phasecal.rig/1"
kind = "hardware"
name = "gige"
[screen]
pitch_mm = [0.2331, 0.2331]
[display]
backend = "sdl"
monitor = 1
[camera]
backend = "aravis"
device = "192.168.10.20"
"""


def phasecal(*args: str, ok: bool = True) -> subprocess.CompletedProcess:
    """Run the installed console script."""
    r = subprocess.run([str(BIN / "phasecal"), *args], capture_output=True, text=True)
    print(f"$ phasecal {' '.join(args)} -> {r.returncode}: {(r.stdout + r.stderr).strip()[:300]}")
    if ok and r.returncode != 0:
        sys.exit(f"phasecal {args[0]} failed")
    return r


def serve(work: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    env = dict(os.environ, PHASECAL_DATA_DIR=str(work / "data"))
    proc = subprocess.Popen([str(BIN / "phasecal"), "serve", "--port", str(port), "--rig",
                             "simulated"], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    for _ in range(600):
        try:
            with PhasecalClient(url, retries=0) as c:
                c.health()
            return proc, url
        except Exception:
            time.sleep(0.1)
    proc.kill()
    sys.exit("serve did not answer")


def main() -> None:
    work = Path(sys.argv[1])
    for module in ("pygame", "gi", "usb", "distributed"):
        try:
            __import__(module)
        except ImportError:
            continue
        sys.exit(f"{module} is importable: the venv is not extra-free")
    phasecal("--version")
    phasecal("plan", "--preset", "fast", "--screen-width-px", "320", "--screen-height-px", "240",
             "--pitch-mm", "0.5", "-o", str(work / "plan.json"))
    proc, url = serve(work)
    try:
        with PhasecalClient(url) as c:
            rig = c.create_rig("small", demo_rig_config(160, 120, "mild_pinhole", SCREEN))
            ses = c.create_session("fresh", rig_id=rig["id"], preset="fast")
            server_plan = c.get_plan(ses)
            cli_plan = json.loads((work / "plan.json").read_text())
            if server_plan["frames"] != cli_plan["frames"]:
                sys.exit("the CLI plan differs from the service's plan of the same preset")
            poses = random_poses(mild_pinhole(160, 120), SCREEN, 3, np.random.default_rng(11))
            frames = []
            for p in poses:
                rvec, _ = cv2.Rodrigues(np.asarray(p.rotation, np.float64))
                job = c.wait(c.capture_pose(ses, {"rvec": rvec.ravel().tolist(),
                                                  "tvec_mm": list(map(float, p.translation))}),
                             timeout_s=600)
                pose_id = job["resource"].rsplit("/", 1)[-1]
                folder = work / f"frames{len(frames)}"
                with zipfile.ZipFile(c.download_frames(ses, pose_id, work / "f.zip")) as zf:
                    zf.extractall(folder)
                frames.append(folder)
            print(f"served and captured {len(frames)} poses over HTTP")
    finally:
        proc.terminate()
        proc.wait(30)
    maps = []
    for i, folder in enumerate(frames):
        out = work / f"maps{i}.npz"
        phasecal("decode", "--plan", str(work / "plan.json"), "--frames", str(folder), "-o",
                 str(out))
        maps.append(str(out))
    phasecal("calibrate", "--plan", str(work / "plan.json"), "--maps", *maps, "--model",
             "opencv5", "-o", str(work / "model.json"))
    for fmt, name in (("opencv-yaml", "cam.yaml"), ("ros", "ros.yaml"),
                      ("mrcal", "cam.cameramodel")):
        phasecal("export", "--model", str(work / "model.json"), "--format", fmt, "-o",
                 str(work / name))
    (work / "aravis.toml").write_text(ARAVIS_RIG)
    r = phasecal("check", "--rig", str(work / "aravis.toml"), ok=False)
    if r.returncode != 1 or "pip install 'phasecal[aravis,sdl]'" not in r.stderr:
        sys.exit("an Aravis rig without the extra did not name the install command")
    print("fresh venv flow: ok")


if __name__ == "__main__":
    main()
