"""`phasecal auto`: the closed loop on a rig with a mover, without the service: starting
moves around the robot's pose, hand-eye, then the planned pose the robot can reach, each
captured and decoded into DIR, until the target is met or the budget spent (docs/robots.md).

DIR gets plan.json, one folder per pose (pose-NN: frame store and maps.npz, as `phasecal
capture` writes), robot-poses.json (phasecal.robot-poses/1 keyed by those folders),
handeye.json (phasecal.handeye/1, the latest fit) and auto.json (the run's log). Ctrl-C
stops the mover at once; the poses taken stay."""

from __future__ import annotations

import argparse
import json
import signal
import threading
from pathlib import Path
from typing import Any

from acquisition.patterns import build_plan
from acquisition.rig import load_rig_config, open_rig
from api.cli import UserError
from api.jobs.auto import AutoLoop, auto_plan_task, rig_mover
from api.pose_path import MAPS, ThreadDecode, capture_live
from api.progress import progress_bar
from calibration.shared.atomic import write_json_atomic
from calibration.shared.plan import Plan, read_plan
from calibration.shared.progress import Cancelled, TaskContext
from hw_mocks.rig import open_simulated_rig

MOUNTS = ("eye-in-hand", "eye-to-hand")
PLANNING_MODELS = ("opencv5", "opencv-rational", "fisheye")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", required=True, help="rig config (.toml/.json) with a mover section")
    p.add_argument("--target-sigma-urad", required=True, type=float, metavar="URAD",
                   help="stop when the worst predicted 1-sigma ray uncertainty is this low")
    p.add_argument("--handeye-sigma-mm", type=float, metavar="MM",
                   help="and the hand-eye's translation 1-sigma this low")
    p.add_argument("--handeye-sigma-mrad", type=float, metavar="MRAD",
                   help="and the hand-eye's rotation 1-sigma this low")
    p.add_argument("--budget", required=True, type=int, metavar="N",
                   help="the most poses to take (>= 4: the starting set)")
    p.add_argument("--mount", choices=MOUNTS, default="eye-in-hand",
                   help="eye-in-hand: camera on the flange; eye-to-hand: screen on the flange")
    p.add_argument("--model", choices=PLANNING_MODELS, default="opencv5",
                   help="parametric model the planning and the hand-eye fit use")
    p.add_argument("--plan", help="pattern plan (default: the 'fast' preset for the rig's "
                                  "screen)")
    p.add_argument("--noise-dn", type=float, metavar="SIGMA",
                   help="per-frame camera noise sigma in DN (default: estimated)")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="output folder")


def _check(args: argparse.Namespace) -> None:
    if not args.target_sigma_urad > 0:
        raise UserError(f"--target-sigma-urad: must be > 0, got {args.target_sigma_urad}")
    if args.budget < 4:
        raise UserError(f"--budget: the starting set alone takes 4 poses, got {args.budget}")
    for flag, value in (("--handeye-sigma-mm", args.handeye_sigma_mm),
                        ("--handeye-sigma-mrad", args.handeye_sigma_mrad),
                        ("--noise-dn", args.noise_dn)):
        if value is not None and not value > 0:
            raise UserError(f"{flag}: must be > 0, got {value}")


def run(args: argparse.Namespace) -> int:
    _check(args)
    out = Path(args.output)
    rig = open_rig(load_rig_config(args.rig), simulator=open_simulated_rig)
    try:
        if rig_mover(rig) is None:
            raise UserError(f"{args.rig}: the rig has no mover: add a `mover` section "
                            "(backend = \"http\" for a robot server, see docs/robots.md)")
        screen = rig.screen
        plan = read_plan(args.plan) if args.plan else build_plan(
            screen.width_px, screen.height_px, list(screen.pitch_mm), preset="fast")
        out.mkdir(parents=True, exist_ok=True)
        if any(out.glob("pose-*")):
            raise UserError(f"{out}: holds poses of an earlier run; give a new folder")
        return _loop(args, rig, plan, out)
    finally:
        rig.close()


def _loop(args: argparse.Namespace, rig: Any, plan: Plan, out: Path) -> int:
    """Run the loop with Ctrl-C as its cancel; print what it did."""
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        with progress_bar("auto") as update:
            log = auto_run(rig, plan, out, TaskContext("auto", update, stop), mount=args.mount,
                           model=args.model, budget=args.budget,
                           target_urad=args.target_sigma_urad,
                           handeye_mm=args.handeye_sigma_mm,
                           handeye_mrad=args.handeye_sigma_mrad, noise_dn=args.noise_dn)
    except Cancelled:
        kept = sum((pose / MAPS).is_file() for pose in out.glob("pose-*"))
        raise UserError(f"cancelled: the mover was stopped; {kept} poses kept in {out}, "
                        "the log in auto.json") from None
    finally:
        signal.signal(signal.SIGINT, previous)
    _report(log, out)
    return 0


def auto_run(rig: Any, plan: Plan, out: Path, ctx: TaskContext, *, mount: str, model: str,
             budget: int, target_urad: float, handeye_mm: float | None = None,
             handeye_mrad: float | None = None, noise_dn: float | None = None
             ) -> dict[str, Any]:
    """The loop on an opened rig with a mover, each pose captured and decoded into
    `out`/pose-NN (plan.json beside them), the refit on this thread; the log."""
    write_json_atomic(out / "plan.json", plan.to_dict())

    def capture(ctx: TaskContext) -> str:
        name = f"pose-{len(list(out.glob('pose-*'))):02d}"
        pose_dir = out / name
        pose_dir.mkdir()
        write_json_atomic(pose_dir / "plan.json", plan.to_dict())
        decode = ThreadDecode(pose_dir / "plan.json", pose_dir, pose_dir / MAPS,
                              noise=noise_dn, meta={"camera": rig.camera.info.name})
        capture_live(ctx, rig, plan, pose_dir, decode)
        decode.result()
        return name

    def refit(ctx: TaskContext, robot: dict[str, Any]) -> dict[str, Any]:
        write_json_atomic(out / "robot-poses.json", robot)
        step = auto_plan_task(ctx, str(out / "plan.json"),
                              {p: str(out / p / MAPS) for p in robot["poses"]}, robot, mount,
                              model)
        if step["handeye"] is not None:
            write_json_atomic(out / "handeye.json", step["handeye"])
        return step

    loop = AutoLoop(rig, mount, model, budget, target_urad, capture, refit,
                    lambda log: write_json_atomic(out / "auto.json", log),
                    lambda name: out / name / MAPS, handeye_mm,
                    handeye_mrad)
    return loop.run(ctx)


def _report(log: dict[str, Any], out: Path) -> None:
    print(f"wrote {out}: {len(log['poses'])} poses, {len(log['skipped'])} planned poses "
          f"skipped as unreachable; stopped: {log['stop_reason']}")
    for k, pose in enumerate(log["poses"]):
        worst = pose["worst_ray_sigma_urad"]
        after = "" if worst is None else f" -> worst ray sigma {worst:.3g} urad"
        print(f"  {k + 1:2d} {pose['pose_id']}: {pose['reason']}{after}")
    he = log["handeye"]
    if he is not None:
        print(f"  hand-eye t_mm {[round(v, 3) for v in he['hand_eye']['t_mm']]}, 1-sigma "
              f"{he['sigma']['translation_mm']:.3g} mm, {he['sigma']['rotation_mrad']:.3g} "
              "mrad (handeye.json)")
    print(json.dumps({"stop_reason": log["stop_reason"],
                      "worst_ray_sigma_urad": log["worst_ray_sigma_urad"]}))
