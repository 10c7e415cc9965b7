"""`phasecal demo`: the whole flow over HTTP on the simulated rig, like a rig script would.

Starts the service in-process on a free loopback port with a simulated distorted
wide-angle camera, creates a session, moves the simulated screen and captures several
poses, calibrates them with a parametric model and with the smooth generic model, and
prints a comparison: RMS residuals, time, and a simulator check.

The service never sees the simulator's truth. The simulator check is made here, outside
it, with `hw_mocks.truth`: the simulated rig's twin, built from the same config, picks the
screen poses (as a person placing the screen would) and measures the fitted rays against
the true camera. A real rig has no such check.
"""

from __future__ import annotations

import io
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from api.client import PhasecalClient, ServiceError
from api.config import ServiceConfig
from api.inprocess import running_service
from calibration.shared.maps import load_maps
from calibration.shared.plan import ScreenGeometry
from hw_mocks.truth import SimulatorTruth


@dataclass
class DemoRow:
    """One calibration of the comparison table."""

    model: str
    status: str
    rms_px: float | None
    ray_median_mrad: float | None
    ray_p95_mrad: float | None
    wall_s: float
    calibration_id: str
    error: str | None = None


def demo_rig_config(width: int, height: int, camera: str = "wide_fisheye",
                    screen: ScreenGeometry | None = None) -> dict[str, Any]:
    """A simulated rig config: truth camera `camera` at width x height, optional screen."""
    cfg: dict[str, Any] = {"kind": "simulated",
                           "camera": {"model": camera, "width": width, "height": height}}
    if screen is not None:
        cfg["screen"] = {"width_px": screen.width_px, "height_px": screen.height_px,
                         "pitch_mm": list(screen.pitch_mm)}
    return cfg


def run_demo(out_dir: Path | None = None, *, poses: int = 5, rig: dict[str, Any] | None = None,
             models: tuple[str, ...], preset: str = "default", seed: int = 7,
             options: dict[str, Any] | None = None, out: TextIO | None = None) -> list[DemoRow]:
    """Run the demo on simulated rig config `rig` (default: the 640x480 wide-angle rig) with
    model `options` for every calibration; returns the table rows (also printed to `out`)."""
    rig = rig if rig is not None else demo_rig_config(640, 480)
    out = out or sys.stdout
    root = Path(out_dir) if out_dir else Path(tempfile.mkdtemp(prefix="phasecal-demo-"))
    root.mkdir(parents=True, exist_ok=True)
    config = ServiceConfig(data_dir=root / "data")
    with running_service(config) as (url, _app):
        client = PhasecalClient(url)
        try:
            rows = _drive(client, root, poses, rig, models, preset, seed, options, out)
            links = _reports(client, rows)
        finally:
            client.close()
    _print_table(rows, root, out)
    _print_links(links, root, out)
    return rows


SERVE_URL = "http://127.0.0.1:8000"  # `phasecal serve`'s default address


def _reports(client: PhasecalClient, rows: list[DemoRow]) -> list[tuple[str, str]]:
    """Draw each calibration's report (and the diff of the first two) while the service runs,
    so they are stored in the data folder; returns (label, path) pairs for the summary."""
    done = [r for r in rows if r.status == "succeeded"]
    links = []
    for r in done:
        client.request("GET", f"/calibrations/{r.calibration_id}/report.html")
        links.append((f"report {r.model}", f"/calibrations/{r.calibration_id}/report.html"))
    if len(done) >= 2:
        a, b = done[0].calibration_id, done[1].calibration_id
        client.get(f"/calibrations/{a}/diff/{b}")
        links.append((f"diff {done[0].model} vs {done[1].model}",
                      f"/calibrations/{a}/diff/{b}/diff.html"))
    return links


def _print_links(links: list[tuple[str, str]], root: Path, out: TextIO) -> None:
    """Where to look: the web page and the reports, once `phasecal serve` runs on the data."""
    data = root / "data"
    lines = [f"\nsee it: phasecal serve --data-dir {data}   then open",
             f"  web page                       {SERVE_URL}/"]
    for label, path in links:
        lines.append(f"  {label:<30} {SERVE_URL}{path}")
        if path.endswith("report.html"):
            page = data / "calibrations" / path.split("/")[2] / "report" / "report.html"
            lines.append(f"  {'':<30} (file: {page})")
    out.write("\n".join(lines) + "\n")


def _drive(client: PhasecalClient, root: Path, n_poses: int, rig_config: dict[str, Any],
           models: tuple[str, ...], preset: str, seed: int, options: dict[str, Any] | None,
           out: TextIO) -> list[DemoRow]:
    print(f"phasecal demo: service at {client.http.base_url}, data in {root / 'data'}", file=out)
    rig = client.create_rig("demo", rig_config)
    session = client.create_session("demo", rig_id=rig["id"], preset=preset)
    print(f"session {session['id']}: {session['frame_count']} patterns per pose", file=out)
    # simulator check: the rig's twin, outside the service (hw_mocks.truth)
    truth = SimulatorTruth.from_config(rig_config)
    pose_ids: list[str] = []
    for k, screen_pose in enumerate(truth.screen_poses(n_poses, seed)):
        t0 = time.perf_counter()
        job = client.wait(client.capture_pose(session, screen_pose))  # JobFailed if it fails
        pose_id = (job["resource"] or "").rsplit("/", 1)[-1]
        info = client.get_pose(session, pose_id)
        print(f"pose {k}: {info['valid_pixels']} valid pixels "
              f"({time.perf_counter() - t0:.1f} s)", file=out)
        pose_ids.append(pose_id)
    covered = _covered_pixels(client, session["id"], pose_ids)
    rows = []
    for model in models:
        t0 = time.perf_counter()
        job = client.wait(client.calibrate(session, model, options=options), timeout_s=1800,
                          check=False)
        cal_id = (job["resource"] or "").rsplit("/", 1)[-1]
        cal = client.get_calibration(cal_id)
        wall = time.perf_counter() - t0
        if cal["status"] != "succeeded":
            rows.append(DemoRow(model, cal["status"], None, None, None, wall, cal_id, cal["error"]))
            continue
        med, p95 = _ray_error(client, cal_id, truth, covered)
        rows.append(DemoRow(model, "succeeded", (cal["stats"] or {}).get("rms_px"), med, p95,
                            wall, cal_id))
        print(f"calibrated {model}: {wall:.1f} s; {_export_mrcal(client, cal_id, model, root)}",
              file=out)
        screen = (cal["stats"] or {}).get("screen") or {}
        if screen.get("mode") == "fit":
            std = screen.get("std", {})
            print("  screen fit: " + ", ".join(
                f"{k} {screen[k]:.4f} +- {std.get(k, float('nan')):.4f}"
                for k in ("bow_x_mm", "bow_y_mm", "twist_mm", "glass_mm") if k in screen),
                file=out)
    return rows


def _export_mrcal(client: PhasecalClient, cal_id: str, model: str, root: Path) -> str:
    """Download the calibration as an mrcal .cameramodel; a one-line account of it."""
    dest = root / "exports" / f"{model}.cameramodel"
    dest.parent.mkdir(exist_ok=True)
    try:
        info = client.export(cal_id, "mrcal", dest, approximate=True)
    except ServiceError as exc:
        return f"no mrcal export ({exc.detail})"
    resid = info.get("residual")
    how = "exact" if info.get("exact") else f"spline fit, RMS {resid['rms_px']:.2g} px"
    return f"mrcal model {dest} ({how})"


def _covered_pixels(client: PhasecalClient, session_id: str, pose_ids: list[str],
                    stride: int = 8) -> np.ndarray:
    """Pixels (N, 2) on a grid where at least one pose decoded the screen."""
    union = None
    for pid in pose_ids:
        path = Path(tempfile.mkdtemp(prefix="phasecal-maps-")) / f"{pid}.npz"
        client.download_maps(session_id, pid, path)
        mask = load_maps(path).mask
        path.unlink()
        path.parent.rmdir()
        union = mask if union is None else union | mask
    assert union is not None
    v, u = np.nonzero(union[::stride, ::stride])
    return np.stack([u * stride, v * stride], axis=1).astype(np.float64)


def _ray_error(client: PhasecalClient, cal_id: str, truth: SimulatorTruth,
               pixels: np.ndarray) -> tuple[float, float]:
    """Simulator check: median and 95th percentile angle (mrad) between the rays the service
    unprojects and the simulated camera's true rays (`SimulatorTruth.ray_errors_mrad`)."""
    got = client.unproject(cal_id, pixels.tolist())
    d_fit = np.array([[np.nan] * 3 if r[0] is None else r for r in got["directions"]], float)
    ang = truth.ray_errors_mrad(pixels, d_fit)
    return float(np.median(ang)), float(np.percentile(ang, 95))


def _print_table(rows: list[DemoRow], root: Path, out: TextIO) -> None:
    def fmt(v: float | None, spec: str) -> str:
        return "-" if v is None else format(v, spec)

    buf = io.StringIO()
    buf.write("\nray med/p95: simulator check, fitted rays vs the simulated camera's truth "
              "(hw_mocks.truth, outside the service)\n")
    buf.write(f"{'model':<16} {'status':<10} {'RMS px':>8} {'ray med mrad':>13} "
              f"{'ray p95 mrad':>13} {'time s':>8}\n")
    for r in rows:
        buf.write(f"{r.model:<16} {r.status:<10} {fmt(r.rms_px, '8.4f')} "
                  f"{fmt(r.ray_median_mrad, '13.4f')} {fmt(r.ray_p95_mrad, '13.4f')} "
                  f"{r.wall_s:8.1f}\n")
        if r.error:
            buf.write(f"  {r.model}: {r.error}\n")
    buf.write(f"\noutputs: {root / 'data'} (calibrations/<id>/model.json, opencv.yaml, "
              "residuals.png; sessions, poses with frames and maps.npz); mrcal exports in "
              f"{root / 'exports'}\n")
    out.write(buf.getvalue())
