"""Parametric fits on every pixel, and a real screen (bowed panel behind cover glass).

Table 1, identical pixels (every 8th camera pixel, 6 poses, sigma 0.05 screen px):
OpenCV's own fit of the family (cv2.calibrateCamera / cv2.fisheye.calibrate on all of
those pixels) against phasecal's `points: "sampled"` (OpenCV on 2000 points per pose, the
former default) and `points: "all"` (weighted LM on every given pixel), and phasecal on
every decoded pixel against OpenCV on every 8th. Ray error: RMS angle to the true rays
(after the best rotation) over the pixels that saw the screen, pooled over seeds.
Goals: "all" within 1.1x of OpenCV on the same pixels; all pixels <= 0.25x.

Table 2, real screen (hw_mocks.panel: bow 0.5 mm x, 0.3 mm y, 1.5 mm glass, n 1.52):
`screen: "flat"` and `screen: "fit"` against the flat fit of an ideal screen, with the
screen estimates and their distance from the truth in sigmas. Goals: fit <= 1.5x ideal,
estimates within 3 sigma, flat >= 5x worse. The sGCC rows (`--tables 4`, in the default set;
at --width x --height, every pixel, 6 poses, 10x10 mesh): `sgcc` on the mild pinhole and
`sgcc-noncentral` on the smooth non-central camera (random poses at 150-450 mm), with the
screen fitted jointly with the spline and the poses; ray error = direction RMS after the best
rotation, plus the origin RMS (mm, in the sGCC gauge) for the non-central model; every row
with `family_prior: "off"` (the same free-spline method, so the rows differ only in the
screen).
Table 5 (`--tables 5`): the sGCC screen estimates' z-scores over seeds (honest sigma: RMS ~1).

    .venv/bin/python benchmarks/metrology.py [--width 320 --height 240] [--seeds 6]
        [--step 2] [--tables 1 2 3 4 5]

Table 3 (`--tables 3`, at twice --width/--height): sgcc free (`family_prior: "off"`) and by
default (`"auto"`) against OpenCV's and phasecal's dense fit of the true family on identical
pixels (goal <= 1.5x).
"""

from __future__ import annotations

import argparse
import os
import time

import cv2
import numpy as np

from calibration.compare import in_gauge, ray_angle_difference, sgcc_gauge_transform
from calibration.fit.correspondences import PointSet, point_set
from calibration.fit.dispatch import calibrate
from calibration.metrology.refine import fit_parametric_dense
from calibration.models.parametric import PARAMETRIC_MODELS
from calibration.shared.plan import ScreenGeometry
from hw_mocks import cameras, poses, synthetic
from hw_mocks.panel import PanelShape

SCREEN = ScreenGeometry(1920, 1080, (0.2745, 0.2745))
REAL = PanelShape(bow_x_mm=0.5, bow_y_mm=0.3, glass_mm=1.5, glass_index=1.52)
FAMILIES = {"opencv5": cameras.mild_pinhole, "fisheye": cameras.wide_fisheye}


def _scene(family: str, w: int, h: int, seed: int, panel: PanelShape | None, step: int):
    """Camera, maps' point sets (every `step`-th pixel) and the pixels for the ray error."""
    cam = FAMILIES[family](w, h)
    rng = np.random.default_rng(seed)
    ps = poses.random_poses(cam, SCREEN, 6, rng)
    maps = [synthetic.synthetic_maps(cam, p, SCREEN, rng=rng, sigma_px=0.05, panel=panel)[0]
            for p in ps]
    pts = [point_set(m, SCREEN) for m in maps]
    pts = [p.subset((p.pixels[:, 0] % step == 0) & (p.pixels[:, 1] % step == 0)) for p in pts]
    seen = np.logical_or.reduce([m.mask for m in maps])
    v, u = np.nonzero(seen[::4, ::4])
    return cam, pts, np.stack([u * 4, v * 4], axis=1).astype(np.float64)


def _ray_error(cam, model, pix: np.ndarray) -> float:
    """RMS angle (rad) between the model's and the true rays after the best rotation."""
    return float(ray_angle_difference(model.unproject, lambda p: cam.rays(p[:, 0], p[:, 1]),
                                      (cam.width, cam.height), pixels=pix
                                      )["rms_rad"])


def _opencv(family: str, pts: list[PointSet], size: tuple[int, int]):
    """OpenCV's own fit of the family on exactly these points (fisheye: rational init)."""
    obj = [p.screen_mm.astype(np.float64).reshape(1, -1, 3) for p in pts]
    img = [p.pixels.astype(np.float64).reshape(1, -1, 2) for p in pts]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    k0 = cv2.calibrateCamera([o.reshape(-1, 3).astype(np.float32) for o in obj],
                             [i.reshape(-1, 2).astype(np.float32) for i in img], size, None,
                             None, flags=cv2.CALIB_RATIONAL_MODEL, criteria=crit)[1]
    if family == "fisheye":
        flags = (cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
                 | cv2.CALIB_USE_INTRINSIC_GUESS)
        _, k, d, _, _ = cv2.fisheye.calibrate(obj, img, size, k0.copy(), np.zeros(4),
                                              flags=flags, criteria=crit)
    else:
        _, k, d, _, _ = cv2.calibrateCamera([o.reshape(-1, 3).astype(np.float32) for o in obj],
                                            [i.reshape(-1, 2).astype(np.float32) for i in img],
                                            size, None, None, criteria=crit)
    return PARAMETRIC_MODELS[family](size, k, np.asarray(d).ravel()[:5])


def _pooled(errs: list[float]) -> float:
    """RMS over seeds."""
    return float(np.sqrt(np.mean(np.square(errs))))


def table1(w: int, h: int, seeds: int) -> None:
    """Identical pixels (every 8th) and all pixels against OpenCV on every 8th."""
    print(f"\nTable 1: {w}x{h}, 6 poses, sigma 0.05 screen px, {seeds} seeds "
          "(ray rms pooled over seeds)")
    print(f"{'camera / fit':<46}{'ray rms rad':>12}{'x OpenCV':>10}{'x dense':>9}{'wall s':>8}")
    for family in FAMILIES:
        errs: dict[str, list[float]] = {}
        wall: dict[str, float] = {}
        for seed in range(seeds):
            cam, pts8, pix = _scene(family, w, h, seed, None, 8)
            _, pts1, _ = _scene(family, w, h, seed, None, 1)
            runs = (("OpenCV, every 8th pixel", None, pts8, {}),
                    ("phasecal sampled (2000/pose), every 8th", family, pts8,
                     {"points": "sampled"}),
                    ("phasecal all, every 8th pixel", family, pts8, {}),
                    ("phasecal all, every pixel", family, pts1, {}))
            for label, fam, pts, opts in runs:
                t0 = time.perf_counter()
                model = (_opencv(family, pts, (w, h)) if fam is None
                         else fit_parametric_dense(pts, (w, h), fam, SCREEN, opts)[0])
                wall[label] = wall.get(label, 0.0) + time.perf_counter() - t0
                errs.setdefault(label, []).append(_ray_error(cam, model, pix))
        ref = _pooled(errs["OpenCV, every 8th pixel"])
        for label, e in errs.items():
            print(f"{family + ': ' + label:<46}{_pooled(e):>12.3g}{_pooled(e) / ref:>10.3f}"
                  f"{wall[label] / seeds:>8.1f}")


def table2(w: int, h: int, step: int, seed: int = 11) -> None:
    """Flat vs fitted screen on a bowed panel behind glass, per family."""
    print(f"\nTable 2: {w}x{h}, every {step} px, 6 poses, panel bow 0.5/0.3 mm, glass 1.5 mm "
          f"n 1.52 (seed {seed})")
    print(f"{'family / screen':<28}{'ray rms rad':>12}{'x ideal':>9}{'chi2':>7}{'wall s':>8}"
          f"{'cpu s':>7}  estimates (mm, +-1 sigma, (est - truth)/sigma)")
    truth = {"bow_x_mm": REAL.bow_x_mm, "bow_y_mm": REAL.bow_y_mm, "twist_mm": REAL.twist_mm,
             "glass_mm": REAL.glass_mm}
    for family in FAMILIES:
        cam, ideal_pts, pix = _scene(family, w, h, seed, None, step)
        _, real_pts, _ = _scene(family, w, h, seed, REAL, step)
        ref = None
        for label, pts, screen in (("ideal screen, flat", ideal_pts, "flat"),
                                   ("real screen, flat", real_pts, "flat"),
                                   ("real screen, fit", real_pts, "fit")):
            t0, c0 = time.perf_counter(), time.process_time()
            model, _, _, stats, _ = fit_parametric_dense(pts, (w, h), family, SCREEN,
                                                         {"screen": screen})
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            err = _ray_error(cam, model, pix)
            ref = ref or err
            est = ""
            if screen == "fit":
                s = stats["screen"]
                est = "  ".join(f"{k} {s[k]:.4f}+-{s['std'][k]:.4f} "
                                f"({(s[k] - truth[k]) / s['std'][k]:+.1f})" for k in truth)
            print(f"{family + ': ' + label:<28}{err:>12.3g}{err / ref:>9.2f}"
                  f"{stats['reduced_chi2']:>7.2f}{wall:>8.1f}{cpu:>7.1f}  {est}")


def _sgcc_scene(model: str, w: int, h: int, seed: int, panel: PanelShape | None):
    """Camera and decoded maps of 6 random poses for an sGCC model's row of table 2."""
    central = model == "sgcc"
    cam = cameras.mild_pinhole(w, h) if central else cameras.smooth_noncentral(w, h)
    kw = {} if central else {"distance_mm": (150.0, 450.0), "min_coverage": 0.2}
    rng = np.random.default_rng(seed)
    ps = poses.random_poses(cam, SCREEN, 6, rng, **kw)
    return cam, [synthetic.synthetic_maps(cam, p, SCREEN, rng=rng, sigma_px=0.05,
                                          panel=panel)[0] for p in ps]


def _origin_error(cam, model, w: int, h: int) -> float:
    """RMS origin error (mm) of a non-central sGCC model against the truth, sGCC gauge."""
    truth = lambda p: cam.rays(p[:, 0], p[:, 1])  # noqa: E731
    pix = np.stack(np.meshgrid(np.arange(4, w - 4, 4.0), np.arange(4, h - 4, 4.0)),
                   -1).reshape(-1, 2)
    q, t = sgcc_gauge_transform(truth, (w, h), central=False)
    o, _ = in_gauge(truth, q, t)(pix)
    (comps,) = model.components(pix)
    return float(np.sqrt(np.mean(np.sum((comps[:, 2:] - o[:, :2]) ** 2, axis=1))))


def table2_sgcc(w: int, h: int, seed: int = 11) -> None:
    """Flat vs jointly fitted screen inside sGCC (central and non-central)."""
    print(f"\nTable 2 (sGCC): {w}x{h}, every pixel, 6 poses, 10x10 mesh, same panel (seed {seed})")
    print(f"{'model / screen':<36}{'ray rms rad':>12}{'x ideal':>9}{'origin mm':>11}{'x ideal':>9}"
          f"{'chi2':>7}{'cpu s':>7}  estimates (mm, +-1 sigma, (est - truth)/sigma)")
    truth = {"bow_x_mm": REAL.bow_x_mm, "bow_y_mm": REAL.bow_y_mm, "twist_mm": REAL.twist_mm,
             "glass_mm": REAL.glass_mm}
    for model in ("sgcc", "sgcc-noncentral"):
        ref: tuple[float, float] | None = None
        for label, panel, screen in (("ideal screen, flat", None, "flat"),
                                     ("real screen, flat", REAL, "flat"),
                                     ("real screen, fit", REAL, "fit")):
            cam, maps = _sgcc_scene(model, w, h, seed, panel)
            pix = np.argwhere(np.logical_or.reduce([m.mask for m in maps])[::4, ::4])[:, ::-1]
            t0 = time.process_time()
            # The same (free-spline) method in every row: the comparison is the screen model.
            res = calibrate(maps, SCREEN, model, options={"screen": screen,
                                                          "family_prior": "off"})
            cpu = time.process_time() - t0
            err = _ray_error(cam, res.model, 4.0 * pix)
            org = 0.0 if model == "sgcc" else _origin_error(cam, res.model, w, h)
            ref = ref or (err, org)
            est = ""
            if screen == "fit":
                s = res.stats["screen"]
                est = "  ".join(f"{k} {s[k]:.4f}+-{s['std'][k]:.4f} "
                                f"({(s[k] - truth[k]) / s['std'][k]:+.1f})" for k in truth)
            org_cols = (f"{org:>11.3g}{org / ref[1]:>9.2f}" if ref[1] else f"{'-':>11}{'-':>9}")
            print(f"{model + ': ' + label:<36}{err:>12.3g}{err / ref[0]:>9.2f}{org_cols}"
                  f"{res.stats['chi2_dof']:>7.2f}{cpu:>7.1f}  {est}")


def table5(w: int, h: int, seeds: int) -> None:
    """Is the sGCC screen sigma honest? (estimate - truth) / sigma over seeds, per parameter."""
    print(f"\nTable 5: sGCC screen z-scores, {w}x{h}, 6 poses, 8x8 mesh, {seeds} seeds "
          "(mean and RMS of (estimate - truth) / sigma; RMS ~1 if the sigma is honest)")
    keys = ("bow_x_mm", "bow_y_mm", "twist_mm", "glass_mm")
    truth = np.array([REAL.bow_x_mm, REAL.bow_y_mm, REAL.twist_mm, REAL.glass_mm])
    print(f"{'model':<18}{'':<6}" + "".join(f"{k:>10}" for k in keys))
    for model in ("sgcc", "sgcc-noncentral"):
        z = []
        for seed in range(20, 20 + seeds):
            _, maps = _sgcc_scene(model, w, h, seed, REAL)
            scr = calibrate(maps, SCREEN, model, options={
                "screen": "fit", "cells": [8, 8], "family_prior": "off"}).stats["screen"]
            z.append((np.array([scr[k] for k in keys]) - truth)
                     / np.array([scr["std"][k] for k in keys]))
        za = np.array(z)
        for label, row in (("mean", za.mean(axis=0)), ("rms", np.sqrt((za**2).mean(axis=0)))):
            print(f"{model:<18}{label:<6}" + "".join(f"{v:>10.2f}" for v in row))


def table3(w: int, h: int, seeds: int) -> None:
    """sgcc (free, and with the prior centred on an adequate family) on identical pixels."""
    print(f"\nTable 3: sgcc on identical pixels (every 8th of {w}x{h}, 6 poses, {seeds} seeds)")
    print(f"{'camera / fit':<46}{'ray rms rad':>12}{'x OpenCV':>10}{'x dense':>9}{'wall s':>8}")
    for family in FAMILIES:
        errs: dict[str, list[float]] = {}
        wall: dict[str, float] = {}
        for seed in range(seeds):
            cam = FAMILIES[family](w, h)
            rng = np.random.default_rng(seed)
            ps = poses.random_poses(cam, SCREEN, 6, rng)
            maps = [synthetic.synthetic_maps(cam, p, SCREEN, rng=rng, sigma_px=0.05)[0]
                    for p in ps]
            seen = np.logical_or.reduce([m.mask for m in maps])
            v, u = np.nonzero(seen[::4, ::4])
            pix = np.stack([u * 4, v * 4], axis=1).astype(np.float64)
            for m in maps:
                grid = np.zeros_like(m.mask)
                grid[::8, ::8] = True
                m.mask &= grid
            pts = [point_set(m, SCREEN, reject_outliers=False) for m in maps]
            runs = (("OpenCV, same pixels", None), ("phasecal dense, true family", "dense"),
                    ("sgcc, family_prior off", "off"), ("sgcc, default (auto)", "auto"))
            for label, mode in runs:
                t0 = time.perf_counter()
                if mode is None:
                    model = _opencv(family, pts, (w, h))
                elif mode == "dense":
                    model = fit_parametric_dense(pts, (w, h), family, SCREEN)[0]
                else:
                    model = calibrate(maps, SCREEN, "sgcc", options={"family_prior": mode}).model
                wall[label] = wall.get(label, 0.0) + time.perf_counter() - t0
                errs.setdefault(label, []).append(_ray_error(cam, model, pix))
        ref = _pooled(errs["OpenCV, same pixels"])
        dense = _pooled(errs["phasecal dense, true family"])
        for label, e in errs.items():
            print(f"{family + ': ' + label:<46}{_pooled(e):>12.3g}{_pooled(e) / ref:>10.3f}"
                  f"{_pooled(e) / dense:>9.3f}{wall[label] / seeds:>8.1f}")


def main() -> None:
    """Print the tables asked for."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--step", type=int, default=2,
                    help="table 2 (at twice --width/--height): every step-th pixel")
    ap.add_argument("--tables", type=int, nargs="+", default=[1, 2, 4],
                    help="3: sgcc on identical pixels (at twice --width/--height); 4: table 2's "
                         "sGCC rows (at --width/--height); 5: sGCC screen z-scores (at half "
                         "--width/--height, --seeds + 4 seeds)")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if 1 in args.tables:
        table1(args.width, args.height, args.seeds)
    if 2 in args.tables:
        table2(2 * args.width, 2 * args.height, args.step)
    if 4 in args.tables:
        table2_sgcc(args.width, args.height)
    if 5 in args.tables:
        table5(args.width // 2, args.height // 2, args.seeds + 4)
    if 3 in args.tables:
        table3(2 * args.width, 2 * args.height, args.seeds)


if __name__ == "__main__":
    main()
