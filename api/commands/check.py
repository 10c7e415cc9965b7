"""`phasecal check`: try a rig before a session with the controller's own setup helpers.

Measures the display-to-camera latency, chooses the exposure, shows white and black
flats (screen coverage, saturation) and measures the display response, then prints
what it found and the settings to put in the rig config.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from typing import Any

import numpy as np

from acquisition.camera.pixel_formats import PIXEL_FORMATS
from acquisition.errors import AcquisitionError
from acquisition.flat_check import FlatReport, flat_report
from acquisition.rig import Rig, open_rig, parse_rig_config
from acquisition.setup import (
    choose_exposure,
    grab_settled,
    measure_display_response,
    measure_latency,
)
from api.cli import UserError
from api.rigs import load_default_config
from hw_mocks.rig import open_simulated_rig


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", default="simulated",
                   help="rig config (TOML/JSON) or 'simulated' (default)")
    p.add_argument("--target", type=float, default=0.8,
                   help="white flat level as a fraction of the camera's full scale")
    p.add_argument("--no-response", action="store_true",
                   help="skip the display response (gamma) measurement")
    p.add_argument("--json", action="store_true", help="print the findings as JSON")


def _open(spec: str) -> Rig:
    """Open `simulated` or a rig config file, read the way `phasecal serve --rig` reads it."""
    config = parse_rig_config(load_default_config(spec), f"--rig {spec}")
    return open_rig(config, simulator=open_simulated_rig)


def _gamma(levels: np.ndarray, linear: np.ndarray, top: int) -> float:
    """Best power-law exponent of a measured response (log-log fit on mid levels)."""
    x, y = levels / top, linear
    ok = (x > 0.05) & (y > 0.01) & (y < 0.99)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)[0])


def _flat(display: Any, level: int) -> np.ndarray:
    """A flat image of device code `level` for the display."""
    info = display.info
    return np.full((info.height_px, info.width_px), level,
                   np.uint8 if info.bit_depth == 8 else np.uint16)


def _full_scale(pixel_format: str, bit_depth: int) -> int:
    """Top DN of a pixel format (Mono12 -> 4095), else of the camera's bit depth."""
    fmt = PIXEL_FORMATS.get(pixel_format)
    return (1 << (fmt.bit_depth if fmt is not None else bit_depth)) - 1


def check_rig(rig: Rig, *, target: float = 0.8, response: bool = True) -> dict[str, Any]:
    """Run the checks on an opened rig; returns the findings (JSON-friendly)."""
    display, camera, clock = rig.display, rig.camera, rig.clock
    trig = rig.trigger
    found: dict[str, Any] = {"display": asdict(display.info), "camera": asdict(camera.info)}
    lat = measure_latency(display, camera, clock, rig.settings, trigger_box=trig)
    found["latency"] = asdict(lat)
    # waits after a flip: long enough for every latency the frames could not rule out
    latency_s = max((lat.periods, *lat.undecided)) / display.info.refresh_hz
    exp = choose_exposure(display, camera, clock, rig.settings, latency_s=latency_s,
                          target=target, trigger_box=trig)
    settings = exp.settings
    found["exposure"] = {"exposure_s": settings.exposure_s, "gain_db": settings.gain_db,
                         "level_dn": exp.level_dn, "fraction_of_max": exp.fraction_of_max,
                         "iterations": exp.iterations}
    settle = latency_s + 2.0 / display.info.refresh_hz
    top = (1 << display.info.bit_depth) - 1
    applied = camera.configure(settings)
    camera.start()
    try:
        white = grab_settled(display, camera, clock, applied, _flat(display, top), settle,
                             trigger_box=trig)
        black = grab_settled(display, camera, clock, applied, _flat(display, 0), settle,
                             trigger_box=trig)
    finally:
        camera.stop()
    found["flats"] = asdict(flat_report(white, black, _full_scale(applied.pixel_format,
                                                                   camera.info.bit_depth)))
    if response:
        try:
            # One frame per level: the mean over all lit pixels already averages the noise.
            resp = measure_display_response(display, camera, clock, settings,
                                            latency_s=latency_s, average=1,
                                            trigger_box=trig)
            found["display_response"] = {
                "levels": resp.levels.tolist(), "linear": resp.linear.tolist(),
                "gamma": _gamma(resp.levels, resp.linear, top)}
        except AcquisitionError as exc:
            found["display_response"] = {"error": str(exc)}
    found["settings"] = {"exposure_s": settings.exposure_s, "gain_db": settings.gain_db,
                         "pixel_format": settings.pixel_format,
                         "trigger_mode": settings.trigger_mode}
    return found


def _print(found: dict[str, Any]) -> None:
    d, c = found["display"], found["camera"]
    print(f"display: {d['name']} {d['width_px']}x{d['height_px']} @ {d['refresh_hz']:g} Hz, "
          f"{d['bit_depth']}-bit")
    print(f"camera:  {c['name']} serial {c['serial']} {c['width']}x{c['height']}, "
          f"{c['bit_depth']}-bit, triggers {', '.join(c['trigger_modes'])}")
    lat = found["latency"]
    print(f"latency: {lat['periods']} refresh periods ({1e3 * lat['latency_s']:.1f} ms) from "
          f"{lat['observations']} frames, {lat['violations']} inconsistent")
    e = found["exposure"]
    print(f"exposure: {1e3 * e['exposure_s']:.3f} ms at {e['gain_db']:g} dB puts white at "
          f"{100 * e['fraction_of_max']:.1f}% of full scale ({e['iterations']} tries)")
    for line in FlatReport(**found["flats"]).lines():
        print(line)
    r = found.get("display_response")
    if r is not None:
        if "error" in r:
            print(f"display response: not measured: {r['error']}")
        else:
            mid = len(r["levels"]) // 2
            print(f"display response: gamma ~{r['gamma']:.2f} ({len(r['levels'])} levels; "
                  f"code {r['levels'][mid]:g} -> {r['linear'][mid]:.3f} of white)")
    s = found["settings"]
    print("settings for the rig config:")
    print(f"  [settings]\n  exposure_s = {s['exposure_s']:.6g}\n  gain_db = {s['gain_db']:g}\n"
          f"  pixel_format = \"{s['pixel_format']}\"\n  trigger_mode = \"{s['trigger_mode']}\"")


def run(args: argparse.Namespace) -> int:
    if not 0.05 <= args.target <= 0.98:
        raise UserError(f"--target: expected a fraction in [0.05, 0.98], got {args.target}")
    rig = _open(args.rig)
    try:
        found = check_rig(rig, target=args.target, response=not args.no_response)
    except AcquisitionError as exc:
        raise UserError(f"rig {args.rig}: {exc}") from exc
    finally:
        rig.close()
    if args.json:
        print(json.dumps(found, indent=2))
    else:
        _print(found)
    return 0
