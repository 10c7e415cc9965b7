"""The closed loop against a fixed pose list on the simulated arm: poses, wall and CPU time
to reach a worst-ray-sigma target.

Per seed (the arm's landing errors), a simulated rig (160x120 camera, the 'fast' plan)
whose six-axis arm carries the camera (the simulator's own coupling, `hw_mocks.rig`), the
arm at its home pose, where the camera sees the screen:

- auto: `phasecal auto`'s loop (`api.commands.auto.auto_run`: starting moves, hand-eye,
  planned poses, each captured and decoded from simulated frames) until the target or
  `--budget` poses;
- fixed: `--budget` flange poses planned up front to show varied, well-covered views
  (`HandEyeRig.view_plan`, as an operator's pose list would be), captured the same way; the
  poses it needs are the first prefix whose refit (the same `auto_plan_task`) meets the
  target. Its time to target counts its captures up to that pose and one refit.

Prints per seed and in sum: poses to the target, wall and CPU seconds (process CPU, decode
threads included), the hand-eye translation error against the truth and its stated sigma,
and the worst ray sigma after each pose from the fourth on.

    nice .venv/bin/python -m benchmarks.auto [--seeds 3] [--target-urad 250] [--budget 12]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from acquisition.patterns import build_plan
from acquisition.rig import open_rig, parse_rig_config
from api.commands.auto import auto_run
from api.jobs.auto import auto_plan_task
from api.pose_path import MAPS, ThreadDecode, capture_live
from calibration.shared.atomic import write_json_atomic
from calibration.shared.plan import Plan
from calibration.shared.progress import TaskContext
from hw_mocks.arm import HandEyeRig
from hw_mocks.rig import SimulatedRig, open_simulated_rig
from tests.api.test_auto import RIG

MOUNT, MODEL = "eye-in-hand", "opencv5"


def _rig(seed: int) -> tuple[Any, HandEyeRig, Plan]:
    config = {**RIG, "mover": {**RIG["mover"], "seed": seed}}
    rig = open_rig(parse_rig_config(config, "benchmark rig"), simulator=open_simulated_rig)
    assert isinstance(rig.simulated, SimulatedRig) and rig.simulated.handeye is not None
    truth = rig.simulated.handeye
    s = rig.screen
    return rig, truth, build_plan(s.width_px, s.height_px, list(s.pitch_mm), preset="fast")


def _handeye_error_mm(step: dict[str, Any], truth: HandEyeRig) -> float:
    return float(np.linalg.norm(np.asarray(step["hand_eye"]["t_mm"])
                                - truth.hand_eye.translation_mm))


def run_auto(seed: int, target: float, budget: int, out: Path) -> dict[str, Any]:
    rig, truth, plan = _rig(seed)
    try:
        wall, cpu = time.perf_counter(), time.process_time()
        log = auto_run(rig, plan, out, TaskContext("auto"), mount=MOUNT, model=MODEL,
                       budget=budget, target_urad=target)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    finally:
        rig.close()
    met = log["stop_reason"] == "target met"
    return {"poses": len(log["poses"]) if met else None, "taken": len(log["poses"]),
            "wall_s": wall, "cpu_s": cpu, "worst": log["worst_ray_sigma_urad"],
            "he_err_mm": _handeye_error_mm(log["handeye"], truth),
            "he_sigma_mm": log["handeye"]["sigma"]["translation_mm"],
            "skipped": len(log["skipped"]),
            "curve": [p["worst_ray_sigma_urad"] for p in log["poses"][3:]]}


def run_fixed(seed: int, target: float, budget: int, out: Path) -> dict[str, Any]:
    rig, truth, plan = _rig(seed)
    rng = np.random.default_rng(1000 + seed)
    flanges = truth.view_plan(budget, rng)
    write_json_atomic(out / "plan.json", plan.to_dict())
    info = rig.mover.info
    robot: dict[str, Any] = {"format": "phasecal.robot-poses/1", "poses": {},
                             "repeatability": {"mm": info.repeatability_mm,
                                               "deg": info.repeatability_deg}}
    captured: list[tuple[float, float]] = []  # cumulative wall, CPU after each pose
    wall0, cpu0 = time.perf_counter(), time.process_time()
    try:
        for k, flange in enumerate(flanges):
            reached = rig.move_to(flange)
            pose_dir = out / f"pose-{k:02d}"
            pose_dir.mkdir()
            write_json_atomic(pose_dir / "plan.json", plan.to_dict())
            decode = ThreadDecode(pose_dir / "plan.json", pose_dir, pose_dir / MAPS,
                                  meta={"camera": rig.camera.info.name})
            capture_live(TaskContext("fixed"), rig, plan, pose_dir, decode)
            decode.result()
            robot["poses"][pose_dir.name] = reached.to_json()
            captured.append((time.perf_counter() - wall0, time.process_time() - cpu0))
    finally:
        rig.close()
    result: dict[str, Any] = {"poses": None, "taken": budget, "curve": []}
    for k in range(4, budget + 1):
        names = list(robot["poses"])[:k]
        prefix = {**robot, "poses": {n: robot["poses"][n] for n in names}}
        wall, cpu = time.perf_counter(), time.process_time()
        step = auto_plan_task(TaskContext("fixed"), str(out / "plan.json"),
                              {n: str(out / n / MAPS) for n in names}, prefix, MOUNT, MODEL)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        result["curve"].append(step["worst_ray_sigma_urad"])
        result.update(worst=step["worst_ray_sigma_urad"],
                      he_err_mm=_handeye_error_mm(step["handeye"], truth),
                      he_sigma_mm=step["handeye_sigma"]["translation_mm"],
                      wall_s=captured[k - 1][0] + wall, cpu_s=captured[k - 1][1] + cpu)
        if step["worst_ray_sigma_urad"] <= target:
            result["poses"] = k
            break
    return result


def _row(name: str, seed: int, r: dict[str, Any]) -> str:
    poses = r["poses"] if r["poses"] is not None else f"not in {r['taken']}"
    return (f"| {seed} | {name} | {poses} | {r['worst']:.3g} | {r['wall_s']:.1f} | "
            f"{r['cpu_s']:.1f} | {r['he_err_mm']:.3f} | {r['he_sigma_mm']:.3f} | "
            f"{' '.join(f'{v:.0f}' for v in r['curve'])} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--target-urad", type=float, default=250.0)
    ap.add_argument("--budget", type=int, default=12)
    args = ap.parse_args()
    print(f"target worst ray sigma {args.target_urad:g} urad, budget {args.budget} poses, "
          f"{MODEL}, {MOUNT}")
    print("| seed | run | poses to target | worst sigma at stop (urad) | wall s | CPU s | "
          "hand-eye error mm | hand-eye sigma mm | worst sigma after pose 4, 5, ... |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    totals: dict[str, list[dict[str, Any]]] = {"auto": [], "fixed": []}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seeds):
            for name, fn in (("auto", run_auto), ("fixed", run_fixed)):
                out = Path(tmp) / f"{name}-{seed}"
                out.mkdir()
                r = fn(seed, args.target_urad, args.budget, out)
                totals[name].append(r)
                print(_row(name, seed, r), flush=True)
    for name, rows in totals.items():
        met = [r["poses"] for r in rows if r["poses"] is not None]
        print(f"{name}: target met in {len(met)}/{len(rows)} seeds, mean poses "
              f"{np.mean(met) if met else float('nan'):.1f}, CPU "
              f"{sum(r['cpu_s'] for r in rows):.1f} s in all")


if __name__ == "__main__":
    main()
