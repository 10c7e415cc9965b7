"""`phasecal capture`: capture one pose on a rig into POSE_DIR (raw frames + decoded maps)."""

from __future__ import annotations

import argparse
import json
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from acquisition.rig import load_rig_config, open_rig, parse_rig_config
from api.cli import UserError
from api.pose_path import ThreadDecode, capture_live
from api.progress import progress_bar
from calibration.shared.plan import read_plan
from calibration.shared.progress import TaskContext
from hw_mocks.rig import open_simulated_rig


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", required=True, help="'simulated' or a rig config (.toml/.json)")
    p.add_argument("--plan", required=True, help="pattern plan (phasecal.plan/1 JSON)")
    p.add_argument("--noise-dn", type=float, metavar="SIGMA",
                   help="per-frame camera noise sigma in DN (default: estimated from residuals)")
    p.add_argument("-o", "--output", required=True, metavar="POSE_DIR",
                   help="pose folder: plan.json, frames.npy + frames.done (raw frames, "
                        "resumed if present), maps.npz")


def _open(spec: str) -> Any:
    config = (parse_rig_config({"kind": "simulated"}, "--rig simulated") if spec == "simulated"
              else load_rig_config(spec))
    return open_rig(config, simulator=open_simulated_rig)


def run(args: argparse.Namespace) -> int:
    if args.noise_dn is not None and not args.noise_dn > 0:
        raise UserError(f"--noise-dn: must be > 0 DN, got {args.noise_dn}")
    plan = read_plan(args.plan)
    pose_dir = Path(args.output)
    pose_dir.mkdir(parents=True, exist_ok=True)
    rig = _open(args.rig)
    bars = ExitStack()  # the progress bar (rich, on a terminal only) ends with the capture
    bar = bars.enter_context(progress_bar("capture"))
    try:
        screen = rig.screen
        if (screen.width_px, screen.height_px) != (plan.screen.width_px, plan.screen.height_px):
            raise UserError(f"{args.plan}: plan screen {plan.screen.width_px}x"
                            f"{plan.screen.height_px} px differs from the rig's display "
                            f"{screen.width_px}x{screen.height_px} px")
        (pose_dir / "plan.json").write_text(json.dumps(plan.to_dict(), indent=1))
        decode = ThreadDecode(pose_dir / "plan.json", pose_dir, pose_dir / "maps.npz",
                              noise=args.noise_dn, meta={"camera": rig.camera.info.name})
        try:
            cap = capture_live(TaskContext("capture", bar), rig, plan, pose_dir, decode)
            last_frame = time.perf_counter()
        finally:
            bars.close()
        try:
            res = decode.result()
        except Exception as exc:
            raise UserError(f"decode: {exc}") from exc
        ready = time.perf_counter() - last_frame
    finally:
        bars.close()
        rig.close()
    total = res["width"] * res["height"]
    timing = (f"; {cap['recaptures']} torn frames shown again, latest trigger "
              f"{1e3 * cap['trigger_late_s']:.1f} ms late") if "recaptures" in cap else ""
    print(f"wrote {pose_dir}: {len(plan.frames)} frames (captured {cap['captured']}, "
          f"resumed from {cap['resumed_from']}), maps.npz {res['valid_pixels']} of {total} "
          f"pixels valid ({100.0 * res['valid_pixels'] / total:.1f} %), ready {ready:.2f} s "
          "after the last frame" + timing
          + (f"; FLAGGED: {cap['flagged']}" if cap.get("flagged") else ""))
    return 0
