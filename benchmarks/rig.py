"""Rig extrinsics against simulated truth and against OpenCV, on identical data.

Three simulated rigs (hw_mocks/rig_truth.py): (a) two pinholes 200 mm apart, (b) three
cameras in a row where A and C never see the screen together (tied through B), (c) a
pinhole and a 150-degree fisheye 150 mm apart. Per seed, every camera sees the screen in
8 views per group of cameras, and records
- sparse data: the corners of an 11 x 8 chessboard drawn on the screen, 0.1 px noise;
- dense data: decoded maps, 0.05 screen-px noise (the decoder's sigma), of which the joint
  fit takes `--dense-points` pixels per camera and view;
- the sparse data again with every camera fitted as sgcc (row "sgcc"), and the dense data
  with every camera fitted as sgcc (row "dsgcc": each camera's spline from its own dense fit
  of the decoded maps): each camera's frame is then its sGCC gauge (the ray at the sensor
  centre +z), so the truth is turned into the gauges taken from the true cameras' own rays
  before comparing.
For each camera pair it prints the extrinsics error against the truth (rotation mrad,
translation mm; RMS over seeds), the predicted 1-sigma, the std of the normalized errors
(error / predicted sigma over the 6 components and the seeds: honest near 1), and OpenCV on
the same sparse points: per-camera cv2.calibrateCamera (cv2.fisheye.calibrate), then
cv2.stereoCalibrate with CALIB_FIX_INTRINSIC on the views both cameras see (a pinhole +
fisheye pair on undistorted normalized points; a pair that never sees the screen together
chained through the middle camera). Ratios are ours / OpenCV's error (RMS over seeds):
sparse on identical points (goal <= 1.0), dense on every decoded pixel (goal <= 0.2).

Rerun: `nice .venv/bin/python -P benchmarks/rig.py` (~9 min CPU; `--seeds`, `--case`,
`--kind`).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibration import RigInput, calibrate_rig
from calibration.fit.rig.transforms import to_rvec
from calibration.fit.sgcc.initial import gauge_rotation
from calibration.shared.plan import ScreenGeometry
from hw_mocks.camera_base import TruthCamera
from hw_mocks.cameras import mild_pinhole
from hw_mocks.fisheye_camera import wide_fisheye
from hw_mocks.rig_truth import (
    RigTruth,
    camera_at,
    grid_points,
    shared_views,
    view_maps,
    view_observations,
)

SCREEN = ScreenGeometry(1280, 800, (0.25, 0.25))
W, H = 480, 360
SPARSE_SIGMA_PX = 0.1
DENSE_SIGMA_SCREEN_PX = 0.05
VIEWS_PER_GROUP = 8
KINDS = ("sparse", "dense", "sgcc", "dsgcc")
GAUGED = ("sgcc", "dsgcc")  # rows whose cameras are sGCC: compared in the sGCC gauges


@dataclass
class Case:
    """A simulated rig: cameras (factory, position mm, yaw deg), models, who sees what."""

    cameras: dict[str, tuple]
    models: dict[str, str]
    groups: list[tuple[str, ...]]
    pairs: list[tuple[str, str]]
    distance_mm: tuple[float, float] = (350.0, 550.0)
    min_coverage: float = 0.3  # of each camera's image that sees the screen in a view


CASES = {
    "a": Case({"A": (mild_pinhole, (0.0, 0.0, 0.0), 0.0),
               "B": (mild_pinhole, (200.0, 0.0, 0.0), -10.0)},
              {"A": "opencv5", "B": "opencv5"}, [("A", "B")], [("A", "B")]),
    "b": Case({"A": (mild_pinhole, (0.0, 0.0, 0.0), 14.0),
               "B": (mild_pinhole, (200.0, 0.0, 0.0), 0.0),
               "C": (mild_pinhole, (400.0, 0.0, 0.0), -14.0)},
              {"A": "opencv5", "B": "opencv5", "C": "opencv5"},
              [("A", "B"), ("B", "C")], [("A", "B"), ("A", "C")]),
    "c": Case({"A": (mild_pinhole, (0.0, 0.0, 0.0), 0.0),
               "B": (lambda w, h: wide_fisheye(w, h, 150.0), (150.0, 0.0, 0.0), -8.0)},
              {"A": "opencv5", "B": "fisheye"}, [("A", "B")], [("A", "B")],
              distance_mm=(180.0, 300.0), min_coverage=0.1),
}


def rig_truth(case: Case) -> RigTruth:
    cams, rots, ts = {}, {}, {}
    for name, (factory, pos, yaw) in case.cameras.items():
        cams[name] = factory(W, H)
        rots[name], ts[name] = camera_at(pos, yaw_deg=yaw)
    return RigTruth(cams, rots, ts)


def pose_error(rot: np.ndarray, t: np.ndarray, r_true: np.ndarray, t_true: np.ndarray
               ) -> np.ndarray:
    """(rotation vector error rad, translation error mm) as 6 numbers."""
    return np.concatenate([to_rvec(rot @ r_true.T), t - t_true])


def gauge_frame(cam: TruthCamera) -> np.ndarray:
    """Rotation from a true camera's frame to its sGCC gauge's (the ray at the sensor centre
    +z, the row through it in the x-z plane), from the camera's own rays."""
    cu, cv = (cam.width - 1) / 2, (cam.height - 1) / 2
    _, d = cam.rays(np.array([cu, cu + 1e-3]), np.array([cv, cv]))
    return gauge_rotation(d[0], (d[1] - d[0]) / 1e-3)


def truth_relative(truth: RigTruth, first: str, second: str, gauges: bool
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(R, T) of the pair from the truth, in the sGCC gauges' frames if `gauges`."""
    rot, t = truth.relative(first, second)
    if not gauges:
        return rot, t
    q1, q2 = gauge_frame(truth.cameras[first]), gauge_frame(truth.cameras[second])
    return q2 @ rot @ q1.T, q2 @ t


# -- OpenCV on the same sparse points -----------------------------------------------------
def _seen(obs) -> np.ndarray:
    return np.all(np.isfinite(obs.image_xy), axis=1)


def opencv_intrinsics(model: str, obs_list: list) -> tuple[np.ndarray, np.ndarray]:
    """cv2.calibrateCamera (or cv2.fisheye.calibrate) of one camera on its observations."""
    obj = [o.target_xyz[_seen(o)].astype(np.float32) for o in obs_list]
    img = [o.image_xy[_seen(o)].astype(np.float32) for o in obs_list]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    if model == "fisheye":
        _, k0, _, _, _ = cv2.calibrateCamera(obj, img, (W, H), None, None,
                                             flags=cv2.CALIB_RATIONAL_MODEL, criteria=crit)
        _, k, d, _, _ = cv2.fisheye.calibrate(
            [o.reshape(1, -1, 3).astype(np.float64) for o in obj],
            [i.reshape(1, -1, 2).astype(np.float64) for i in img], (W, H), k0, np.zeros(4),
            flags=cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
            | cv2.CALIB_USE_INTRINSIC_GUESS, criteria=crit)
        return k, np.asarray(d).ravel()
    _, k, d, _, _ = cv2.calibrateCamera(obj, img, (W, H), None, None, criteria=crit)
    return k, np.asarray(d).ravel()


def _normalized(model: str, k: np.ndarray, d: np.ndarray, px: np.ndarray) -> np.ndarray:
    pts = px.reshape(-1, 1, 2).astype(np.float64)
    if model == "fisheye":
        return cv2.fisheye.undistortPoints(pts, k, d.reshape(1, 4)).reshape(-1, 2)
    return cv2.undistortPoints(pts, k, d).reshape(-1, 2)


def opencv_stereo(case: Case, obs: dict, first: str, second: str
                  ) -> tuple[np.ndarray, np.ndarray]:
    """cv2.stereoCalibrate (CALIB_FIX_INTRINSIC) of two cameras on their shared views."""
    intr = {c: opencv_intrinsics(case.models[c], [o for (cc, _), o in obs.items() if cc == c])
            for c in (first, second)}
    views = sorted({v for (c, v) in obs if c == first} & {v for (c, v) in obs if c == second})
    obj, p1, p2 = [], [], []
    for v in views:
        a, b = obs[(first, v)], obs[(second, v)]
        both = _seen(a) & _seen(b)
        obj.append(a.target_xyz[both].astype(np.float32))
        p1.append(_normalized(case.models[first], *intr[first], a.image_xy[both]))
        p2.append(_normalized(case.models[second], *intr[second], b.image_xy[both]))
    eye, zero = np.eye(3), np.zeros(5)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    out = cv2.stereoCalibrate(obj, [p.astype(np.float32) for p in p1],
                              [p.astype(np.float32) for p in p2], eye, zero, eye, zero, (W, H),
                              flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    return out[5], out[6].ravel()


def opencv_relative(case: Case, obs: dict, first: str, second: str
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The pair directly when it shares views, else chained through a camera both share."""
    views = {c: {v for (cc, v) in obs if cc == c} for c in case.cameras}
    if views[first] & views[second]:
        return opencv_stereo(case, obs, first, second)
    mid = next(c for c in case.cameras if views[c] & views[first] and views[c] & views[second])
    r1, t1 = opencv_stereo(case, obs, first, mid)
    r2, t2 = opencv_stereo(case, obs, mid, second)
    return r2 @ r1, r2 @ t1 + t2


# -- one seed -----------------------------------------------------------------------------
def run_seed(case: Case, seed: int, dense_points: int, kinds: list[str]) -> dict:
    rng = np.random.default_rng(seed)
    truth = rig_truth(case)
    views = shared_views(truth, SCREEN, case.groups, VIEWS_PER_GROUP, rng,
                         distance_mm=case.distance_mm, min_coverage=case.min_coverage)
    board = grid_points(SCREEN, 11, 8)
    obs, sparse, dense = {}, [], []
    for k, (group, view) in enumerate(views):
        for c in group:
            o = view_observations(truth, c, view, board, sigma_px=SPARSE_SIGMA_PX, rng=rng)
            obs[(c, f"v{k}")] = o
            sparse.append(RigInput(c, f"v{k}", observations=o))
            dense.append(RigInput(c, f"v{k}", maps=view_maps(
                truth, c, view, SCREEN, sigma_px=DENSE_SIGMA_SCREEN_PX, rng=rng)))
    out: dict = {"cpu": {}}
    sgcc = {c: "sgcc" for c in case.cameras}
    for kind, inputs, opts, models in (
            ("sparse", sparse, {}, case.models),
            ("dense", dense, {"max_points_per_view": dense_points}, case.models),
            ("sgcc", sparse, {}, sgcc),
            ("dsgcc", dense, {"max_points_per_view": dense_points}, sgcc)):
        if kinds and kind not in kinds:
            continue
        t0 = time.process_time()
        res = calibrate_rig(inputs, models, SCREEN, options=opts, reference="A")
        out["cpu"][kind] = time.process_time() - t0
        for first, second in case.pairs:
            rot, t = res.rig.relative(first, second)
            err = pose_error(rot, t, *truth_relative(truth, first, second,
                                                        kind in GAUGED))
            sd = np.sqrt(np.diag(res.rig.camera(second).covariance))  # first is "A"
            out[(kind, first, second)] = (err, sd)
    t0 = time.process_time()
    for first, second in case.pairs:
        rot, t = opencv_relative(case, obs, first, second)
        out[("opencv", first, second)] = (pose_error(rot, t, *truth.relative(first, second)),
                                          None)
    out["cpu"]["opencv"] = time.process_time() - t0
    return out


def _rms(errs: list[np.ndarray], part: slice) -> float:
    return float(np.sqrt(np.mean([np.sum(e[part] ** 2) for e in errs])))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--case", choices=sorted(CASES), action="append")
    ap.add_argument("--kind", choices=KINDS, action="append",
                    help="rows to run (default all)")
    ap.add_argument("--dense-points", type=int, default=4000,
                    help="decoded pixels per camera and view in the dense fit")
    args = ap.parse_args()
    rot, tr = slice(0, 3), slice(3, 6)
    print(f"{W}x{H} cameras, {VIEWS_PER_GROUP} views per group, sparse 11x8 corners at "
          f"{SPARSE_SIGMA_PX} px, dense {args.dense_points} px/view at "
          f"{DENSE_SIGMA_SCREEN_PX} screen px; {args.seeds} seeds; errors RMS over seeds")
    print(f"{'case':4} {'pair':4} {'data':6} {'rot mrad':>9} {'sig mrad':>9} {'t mm':>8} "
          f"{'sig mm':>8} {'z std':>6} {'cv rot':>8} {'cv t':>8} {'ratio r':>7} {'ratio t':>7} "
          f"{'cpu s':>6}")
    for name in args.case or sorted(CASES):
        case = CASES[name]
        kinds = args.kind or list(KINDS)
        runs = [run_seed(case, s, args.dense_points, kinds) for s in range(args.seeds)]
        for first, second in case.pairs:
            cv = [r[("opencv", first, second)][0] for r in runs]
            for kind in kinds:
                errs = [r[(kind, first, second)][0] for r in runs]
                sds = [r[(kind, first, second)][1] for r in runs]
                z = np.concatenate([e / s for e, s in zip(errs, sds, strict=True)])
                cpu = np.mean([r["cpu"][kind] for r in runs])
                print(f"{name:4} {first + second:4} {kind:6} {_rms(errs, rot) * 1e3:9.4f} "
                      f"{np.sqrt(np.mean([np.sum(s[rot] ** 2) for s in sds])) * 1e3:9.4f} "
                      f"{_rms(errs, tr):8.4f} "
                      f"{np.sqrt(np.mean([np.sum(s[tr] ** 2) for s in sds])):8.4f} "
                      f"{np.std(z):6.2f} {_rms(cv, rot) * 1e3:8.4f} {_rms(cv, tr):8.4f} "
                      f"{_rms(errs, rot) / _rms(cv, rot):7.3f} "
                      f"{_rms(errs, tr) / _rms(cv, tr):7.3f} {cpu:6.2f}")
        print(f"     OpenCV cpu s per seed: {np.mean([r['cpu']['opencv'] for r in runs]):.2f}")


if __name__ == "__main__":
    main()
