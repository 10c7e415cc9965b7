"""The classical hand-eye methods against OpenCV's own on the same noisy motions.

The OpenCV wheel pinned for phasecal has no `calibrateHandEye` (only its constants), so the
methods are phasecal's; Debian's OpenCV 4 (python3-opencv, in the system Python beside
python3-mrcal) has them, and here it solves the same eye-in-hand data. Tsai, Park, Horaud,
Daniilidis and Shah's rotation give OpenCV's answer to rounding; Andreff, Li and Shah's
translation are solved differently there (rotation and translation in one linear system)
and must agree within the data's own noise.
"""

from __future__ import annotations

import json
import os
import subprocess

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.handeye.classical import AX_XB_METHODS, AX_ZB_METHODS, chain, classical
from calibration.handeye.rigid import Rigid
from tests.calibration.test_exports import SYSTEM_PYTHON, mrcal_available

OPENCV = r'''
import cv2, json, sys
import numpy as np
d = json.load(sys.stdin)
Rg = [np.array(r) for r in d["Rg"]]; tg = [np.array(t).reshape(3, 1) for t in d["tg"]]
Rt = [np.array(r) for r in d["Rt"]]; tt = [np.array(t).reshape(3, 1) for t in d["tt"]]
out = {}
for name in ("tsai", "park", "horaud", "andreff", "daniilidis"):
    R, t = cv2.calibrateHandEye(Rg, tg, Rt, tt,
                                method=getattr(cv2, "CALIB_HAND_EYE_" + name.upper()))
    out[name] = [R.tolist(), t.ravel().tolist()]
Rb = [r.T for r in Rg]; tb = [-r.T @ t for r, t in zip(Rg, tg)]
for name in ("shah", "li"):
    res = cv2.calibrateRobotWorldHandEye(
        Rt, tt, Rb, tb, method=getattr(cv2, "CALIB_ROBOT_WORLD_HAND_EYE_" + name.upper()))
    R2, t2 = np.asarray(res[2]), np.asarray(res[3]).ravel()  # gripper -> camera
    out[name] = [R2.T.tolist(), (-R2.T @ t2).tolist()]
print(json.dumps(out))
'''
# The system OpenCV comes with python3-mrcal (scripts/install-system-deps.sh): in CI always.
needs_system_opencv = pytest.mark.skipif(not os.environ.get("CI") and not mrcal_available(),
                                         reason="Debian python3-opencv / python3-mrcal missing")


def _motions(rng: np.random.Generator) -> tuple[Rigid, list[Rigid], list[Rigid]]:
    """Eye-in-hand: the camera in the flange (x), ten flange poses, and the target's pose in
    the camera seen with 1 mrad / 0.2 mm noise."""
    def rigid(scale_mm: float) -> Rigid:
        return Rigid(Rotation.from_rotvec(rng.uniform(-1.0, 1.0, 3)).as_matrix(),
                     rng.uniform(-scale_mm, scale_mm, 3))

    x, y = rigid(100), rigid(800)
    flange = [rigid(500) for _ in range(10)]
    seen = []
    for f in flange:
        t = x.inverse() @ chain("eye-in-hand", f).inverse() @ y
        seen.append(Rigid(Rotation.from_rotvec(rng.normal(0, 1e-3, 3)).as_matrix() @ t.rotation,
                          t.translation + rng.normal(0, 0.2, 3)))
    return x, flange, seen


@needs_system_opencv
def test_classical_methods_give_opencvs_answers() -> None:
    x, flange, seen = _motions(np.random.default_rng(5))
    data = {"Rg": [f.rotation.tolist() for f in flange],
            "tg": [f.translation.tolist() for f in flange],
            "Rt": [t.rotation.tolist() for t in seen], "tt": [t.translation.tolist() for t in seen]}
    cv = json.loads(subprocess.run([SYSTEM_PYTHON, "-c", OPENCV], input=json.dumps(data),
                                   capture_output=True, text=True, check=True).stdout)
    for method in (*AX_XB_METHODS, *AX_ZB_METHODS):
        ours, _ = classical(method, "eye-in-hand", flange, seen)  # type: ignore[arg-type]
        rotation, translation = np.array(cv[method][0]), np.array(cv[method][1])
        angle = Rotation.from_matrix(ours.rotation @ rotation.T).magnitude()
        shift = np.linalg.norm(ours.translation - translation)
        noise = Rotation.from_matrix(ours.rotation @ x.rotation.T).magnitude()
        if method in ("tsai", "park", "horaud", "daniilidis"):
            assert angle < 1e-10 and shift < 1e-9, method
        elif method == "shah":
            assert angle < 1e-10, method  # its translation is solved jointly here
            assert shift < 3 * np.linalg.norm(ours.translation - x.translation), method
        else:
            assert angle < 3 * max(noise, 1e-4), method
            assert shift < 3 * max(np.linalg.norm(ours.translation - x.translation), 0.1), method
