"""Hand-eye on the simulated arm: phasecal's joint refinement against the classical methods.

A simulated six-axis arm (hw_mocks.arm; 1-sigma repeatability 0.02 mm and 0.005 deg per axis,
no backlash unless asked) carries the camera (eye-in-hand) or the screen (eye-to-hand) to
`--views` poses planned to show varied, well-covered views. The camera sees the screen
through the simulator's dense correspondences with decode-level noise
(hw_mocks.synthetic.synthetic_maps, 0.05 screen px per coordinate), not decoded frames, or
(`--source observations`) as a sparse 9x6 grid of screen points with `--pixel-sigma` noise.
Per seed, the hand-eye entry fits the camera (opencv5), the views' poses and the hand-eye.

Prints per mounting: the hand-eye error against the truth (RMS over seeds, mm and mrad) of
every classical method on the same view poses and of the joint refinement, the joint's
predicted 1-sigma, the spread of its normalized errors (error / stated sigma per component,
std over seeds; 1 is honest), the held-out error beside its expectation, and CPU seconds.

    nice .venv/bin/python benchmarks/handeye.py [--seeds 10] [--views 12] [--backlash-mm 0]
        [--source maps|observations] [--pixel-sigma 0.2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from calibration import handeye_from_maps
from calibration.handeye.pipeline import handeye_from_observations
from calibration.handeye.rigid import Rigid
from calibration.handeye.robot_poses import RobotPoses
from calibration.shared.observations import TargetObservations
from calibration.shared.plan import ScreenGeometry
from hw_mocks.arm import HandEyeRig, handeye_rig
from hw_mocks.cameras import mild_pinhole
from hw_mocks.synthetic import synthetic_maps

CAMERA = mild_pinhole(320, 240)
SCREEN = ScreenGeometry(640, 360, (0.5, 0.5))
REPEATABILITY_MM, REPEATABILITY_DEG = 0.02, 0.005


class _Plan:
    """The part of a plan the hand-eye reads: the screen."""

    screen = SCREEN


def _run(mount: str, seed: int, views: int, backlash_mm: float, source: str,
         pixel_sigma: float) -> tuple[dict, HandEyeRig]:
    rng = np.random.default_rng(seed)
    rig = handeye_rig(mount, CAMERA, SCREEN, rng, repeatability_mm=REPEATABILITY_MM,  # type: ignore[arg-type]
                      repeatability_deg=REPEATABILITY_DEG, backlash_mm=backlash_mm,
                      speed_mm_s=1e6, speed_deg_s=1e6, settle_s=0.0)
    gx, gy = np.meshgrid(np.linspace(20, 620, 9), np.linspace(15, 345, 6))  # screen px
    grid = np.stack([gx.ravel() * SCREEN.pitch_mm[0], gy.ravel() * SCREEN.pitch_mm[1],
                     np.zeros(gx.size)], 1)
    maps, obs, poses = {}, {}, {}
    for k, flange in enumerate(rig.view_plan(views, rng)):
        reported = rig.arm.move_to(flange, 1.0)
        poses[f"v{k}"] = Rigid(reported.rotation, reported.translation_mm)
        seen = rig.screen_pose()
        if source == "maps":
            maps[f"v{k}"], _ = synthetic_maps(CAMERA, seen, SCREEN, sigma_px=0.05, rng=rng,
                                              pose_id=f"v{k}")
        else:
            xy = CAMERA.project(seen.screen_to_camera(grid))
            xy += pixel_sigma * rng.standard_normal(xy.shape)
            obs[f"v{k}"] = TargetObservations(xy, grid, (CAMERA.width, CAMERA.height),
                                              sigma_px=pixel_sigma)
    robot = RobotPoses(poses, REPEATABILITY_MM, REPEATABILITY_DEG)
    if source == "maps":
        return handeye_from_maps(mount, robot, _Plan(), maps, "opencv5"), rig  # type: ignore[arg-type]
    return handeye_from_observations(mount, robot, obs, "opencv5"), rig  # type: ignore[arg-type]


def _error(found: dict, truth: Rigid) -> np.ndarray:
    return Rigid(np.array(found["R"]), np.array(found["t_mm"])).minus(truth)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--backlash-mm", type=float, default=0.0)
    ap.add_argument("--source", choices=["maps", "observations"], default="maps",
                    help="observations: a 9x6 grid of screen points seen with --pixel-sigma "
                         "noise instead of dense maps")
    ap.add_argument("--pixel-sigma", type=float, default=0.2)
    args = ap.parse_args()
    for mount in ("eye-in-hand", "eye-to-hand"):
        errors: dict[str, list[np.ndarray]] = {}
        normalized, sigmas, held = [], [], []
        cpu0 = time.process_time()
        for seed in range(args.seeds):
            doc, rig = _run(mount, seed, args.views, args.backlash_mm, args.source,
                            args.pixel_sigma)
            truth = Rigid(rig.hand_eye.rotation, rig.hand_eye.translation_mm)
            for name, found in doc["stats"]["classical_methods"].items():
                if "error" not in found:
                    errors.setdefault(name, []).append(_error(found["hand_eye"], truth))
            err = _error(doc["hand_eye"], truth)
            errors.setdefault("phasecal joint", []).append(err)
            sigma = np.sqrt(np.diag(doc["hand_eye"]["covariance"]))
            normalized.append(err / sigma)
            sigmas.append(doc["stats"]["hand_eye_sigma"])
            held.append(doc["heldout"])
        cpu = time.process_time() - cpu0
        data = ("dense maps" if args.source == "maps" else
                f"9x6 observations at {args.pixel_sigma} px")
        print(f"\n{mount}, {data}: {args.seeds} seeds x {args.views} views, repeatability "
              f"{REPEATABILITY_MM} mm / {REPEATABILITY_DEG} deg, backlash {args.backlash_mm} mm,"
              f" {cpu:.1f} s CPU ({cpu / args.seeds:.2f} s per hand-eye incl. camera fit)")
        print("| method | hand-eye error RMS mm | RMS mrad |")
        print("| --- | ---: | ---: |")
        rms: dict[str, tuple[float, float]] = {}
        for name, errs in errors.items():
            e = np.array(errs)
            rms[name] = (float(np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, 1)))),
                         float(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, 1))) * 1e3))
            print(f"| {name} | {rms[name][0]:.4f} | {rms[name][1]:.4f} |")
        classical = {k: v for k, v in rms.items() if k != "phasecal joint"}
        best_mm = min(classical, key=lambda k: classical[k][0])
        best_mrad = min(classical, key=lambda k: classical[k][1])
        joint = rms["phasecal joint"]
        print(f"joint / best classical: {joint[0] / classical[best_mm][0]:.2f} in mm "
              f"({best_mm}), {joint[1] / classical[best_mrad][1]:.2f} in mrad ({best_mrad})")
        n = np.array(normalized)
        print(f"joint predicted 1-sigma (RMS over seeds): "
              f"{np.sqrt(np.mean([s['translation_mm'] ** 2 for s in sigmas])):.4f} mm, "
              f"{np.sqrt(np.mean([s['rotation_mrad'] ** 2 for s in sigmas])):.4f} mrad; "
              f"normalized error std {n[:, 3:].std():.2f} (translation), "
              f"{n[:, :3].std():.2f} (rotation), {n.std():.2f} (all)")
        print(f"held out (leave one view out, at the target's center): RMS "
              f"{np.sqrt(np.mean([h['rms_mm'] ** 2 for h in held])):.4f} mm, "
              f"{np.sqrt(np.mean([h['rms_deg'] ** 2 for h in held])):.5f} deg; expected "
              f"{np.sqrt(np.mean([h['expected_rms_mm'] ** 2 for h in held])):.4f} mm, "
              f"{np.sqrt(np.mean([h['expected_rms_deg'] ** 2 for h in held])):.5f} deg; "
              f"normalized mean {np.mean([h['normalized_mean'] for h in held]):.2f}")


if __name__ == "__main__":
    main()
