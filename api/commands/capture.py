"""`phasecal capture`: capture one pose on a rig into POSE_DIR (raw frames + decoded maps).

A rig of several cameras captures them in sync, each camera into its own folder of the pose
(`cameras/<name>/`: frame store, maps.npz, decode.json), as a capture job of the service
lays them out, and decodes every camera live on threads of this command."""

from __future__ import annotations

import argparse
import json
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from acquisition.rig import DEFAULT_CAMERA, load_rig_config, open_rig, parse_rig_config
from api.cli import UserError
from api.pose_path import (
    CAMERA_SUMMARY,
    MAPS,
    LiveDecode,
    ThreadDecode,
    ThreadRigDecode,
    camera_dirs,
    capture_live,
    capture_rig_live,
    pose_camera_names,
    write_camera_names,
)
from api.progress import progress_bar
from calibration.shared.atomic import write_json_atomic
from calibration.shared.frame_store import FrameStore
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
                        "resumed if present), maps.npz; a rig of several cameras: "
                        "cameras.json and cameras/<name>/ with each camera's")


def _open(spec: str) -> Any:
    config = (parse_rig_config({"kind": "simulated"}, "--rig simulated") if spec == "simulated"
              else load_rig_config(spec))
    return open_rig(config, simulator=open_simulated_rig)


def _start_decode(rig: Any, pose_dir: Path, noise: float | None) -> LiveDecode:
    """The live decode of every camera's store, started before the first frame; a pose
    folder captured with other cameras is refused (its stores would not match)."""
    names = list(rig.cameras)
    before = pose_camera_names(pose_dir)
    several = len(names) > 1
    if not before and FrameStore(pose_dir).exists():
        before = [DEFAULT_CAMERA]  # a one-camera pose's store lies in the pose folder
    if before and before != (names if several else [DEFAULT_CAMERA]):
        had = f"cameras {before}" if before != [DEFAULT_CAMERA] else "one camera"
        now = f"cameras {names}" if several else "one camera"
        raise UserError(f"{pose_dir}: the pose was captured with {had}; the rig has {now}: "
                        "capture into a new folder")
    plan_path = pose_dir / "plan.json"
    if not several:
        return ThreadDecode(plan_path, pose_dir, pose_dir / MAPS, noise=noise,
                            meta={"camera": rig.camera.info.name})
    write_camera_names(pose_dir, names)
    dirs = camera_dirs(pose_dir, names)
    return ThreadRigDecode(plan_path, {
        name: (dirs[name], dirs[name] / MAPS,
               {"camera": cam.info.name, "camera_name": name})
        for name, cam in rig.cameras.items()}, noise=noise)


def run(args: argparse.Namespace) -> int:
    if args.noise_dn is not None and not args.noise_dn > 0:
        raise UserError(f"--noise-dn: must be > 0 DN, got {args.noise_dn}")
    plan = read_plan(args.plan)
    pose_dir = Path(args.output)
    pose_dir.mkdir(parents=True, exist_ok=True)
    rig = _open(args.rig)
    names = list(rig.cameras)
    bars = ExitStack()  # the progress bar (rich, on a terminal only) ends with the capture
    bar = bars.enter_context(progress_bar("capture"))
    try:
        screen = rig.screen
        if (screen.width_px, screen.height_px) != (plan.screen.width_px, plan.screen.height_px):
            raise UserError(f"{args.plan}: plan screen {plan.screen.width_px}x"
                            f"{plan.screen.height_px} px differs from the rig's display "
                            f"{screen.width_px}x{screen.height_px} px")
        (pose_dir / "plan.json").write_text(json.dumps(plan.to_dict(), indent=1))
        decode = _start_decode(rig, pose_dir, args.noise_dn)
        try:
            ctx = TaskContext("capture", bar)
            if len(names) > 1:
                cap = capture_rig_live(ctx, rig, plan, camera_dirs(pose_dir, names), decode)
            else:
                cap = capture_live(ctx, rig, plan, pose_dir, decode)
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
    decoded = {names[0]: res} if len(names) == 1 else res
    if len(names) > 1:  # each camera's size and valid pixels beside its maps, as the service
        for name, folder in camera_dirs(pose_dir, names).items():
            write_json_atomic(folder / CAMERA_SUMMARY, {
                k: decoded[name].get(k) for k in ("valid_pixels", "width", "height")})
    timing = (f"; {cap['recaptures']} torn frames shown again, latest trigger "
              f"{1e3 * cap['trigger_late_s']:.1f} ms late") if "recaptures" in cap else ""
    print(f"wrote {pose_dir}: {len(plan.frames)} frames (captured {cap['captured']}, "
          f"resumed from {cap['resumed_from']}), " + ", ".join(
              _maps_line(name if len(names) > 1 else None, d) for name, d in decoded.items())
          + f", ready {ready:.2f} s after the last frame" + timing
          + (f"; FLAGGED: {cap['flagged']}" if cap.get("flagged") else ""))
    return 0


def _maps_line(camera: str | None, res: dict[str, Any]) -> str:
    """One camera's maps in the summary line (`camera` None on a one-camera rig)."""
    total = res["width"] * res["height"]
    where = f"cameras/{camera}/maps.npz" if camera else "maps.npz"
    return (f"{where} {res['valid_pixels']} of {total} pixels valid "
            f"({100.0 * res['valid_pixels'] / total:.1f} %)")
