"""The quick-intrinsics papers' experiments on simulated data, next to their claims.

Rectangle vanishing points (Lu & Whangbo, "A Practical Camera Calibration System on Mobile
Phones"), general-motion self-calibration (Chang, Wang & Wang, "Camera Self-calibration Based
on the Vanishing Points"), rotation-only self-calibration (Hartley), and the classic RANSAC
and PnP estimators.

Usage: .venv/bin/python benchmarks/seeds.py [--trials 8] [--seed 0] [--no-flats]
Camera: distortion-free pinhole 640x480, fx 520, fy 530 (fy/fx = 1.019), principal point
off-center; hw_mocks two-board scene (boards 240x180 mm, 9x7 corners) and general camera
motion (hw_mocks.rectangles). "err" = the largest of |dfx|/fx, |dfy|/fy, |dcx|/fx, |dcy|/fx
in percent; tables give the median (and the largest) over trials.
Corner noise is isotropic Gaussian (sigma px) on every grid corner.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import time

import numpy as np

from calibration.fit.classic.dlt import ransac_dlt
from calibration.fit.classic.estimate import normalizer
from calibration.fit.classic.homography import fit_homography, ransac_homography
from calibration.fit.classic.lines import Point, fit_line, grid_vanishing_points, intersect
from calibration.fit.classic.quad import find_quads
from calibration.fit.classic.rectangle import rectangle_intrinsics
from calibration.fit.classic.robust import solve_pnp, usac_homography
from calibration.fit.classic.rotation import (
    NotPositiveDefiniteError,
    interview_homographies,
    rotation_intrinsics,
)
from calibration.fit.classic.selfcal import linear_selfcal, selfcal_intrinsics
from calibration.fit.classic.zhang import zhang_intrinsics
from calibration.fit.ransac import DegenerateError, required_iterations
from hw_mocks.cameras import PinholeCamera
from hw_mocks.rectangles import (
    board_pixels,
    general_motion_views,
    two_board_scene,
    white_flat_image,
    whole_screen_poses,
)
from hw_mocks.rig import DEFAULT_SCREEN

CAM = PinholeCamera(640, 480, fx=520.0, fy=530.0, cx=331.0, cy=233.5)
SIZE = (640, 480)
NOISE = (0.0, 0.1, 0.5, 1.0)


def err_pct(k: np.ndarray, cam: PinholeCamera = CAM) -> float:
    """Largest relative error of fx, fy, cx, cy (principal point relative to fx), percent."""
    return 100 * max(abs(k[0, 0] / cam.fx - 1), abs(k[1, 1] / cam.fy - 1),
                     abs(k[0, 2] - cam.cx) / cam.fx, abs(k[1, 2] - cam.cy) / cam.fx)


def fmt(vals: list[float], trials: int | None = None) -> str:
    """Median (max) of a list of errors, '-' when empty; [k/n] when only k of n trials ran."""
    if not vals:
        return "-"
    short = f" [{len(vals)}/{trials}]" if trials is not None and len(vals) < trials else ""
    return f"{np.median(vals):.3g} ({np.max(vals):.3g}){short}"


def outline_vps(grid: np.ndarray) -> tuple[Point, Point]:
    """Vanishing points from the rectangle's outline only (4 corners -> 4 side lines)."""
    c = [grid[0, 0], grid[0, -1], grid[-1, -1], grid[-1, 0]]
    sides = [fit_line(np.linspace(c[k], c[(k + 1) % 4], 3), sigma_px=1.0) for k in range(4)]
    return intersect(sides[0], sides[2]), intersect(sides[1], sides[3])


def seed002(trials: int, rng: np.random.Generator) -> None:
    """Rectangle VPs (both forms) vs Zhang on the same corners."""
    board = two_board_scene()[:1]
    plane = board[0].corners()[..., :2].reshape(-1, 2)  # board 0 lies in the world plane z = 0
    print("\n## Rectangle vanishing points (err %, median (max))")
    print("paper: exact without noise; 'no significant differences' from Zhang (20 views)")
    print("| sigma px | views | eq.4 fx!=fy, grid lines | square px, grid lines "
          "| eq.4, outline only | Zhang (same corners) | eq.4 / Zhang |")
    print("|---|---|---|---|---|---|---|")
    for sigma in NOISE:
        for n in (4, 8, 20):
            e = {"rect": [], "sq": [], "outline": [], "zhang": []}
            for _ in range(trials):
                views = general_motion_views(CAM, board, n, rng)
                px = [p[0] for p in board_pixels(CAM, board, views, sigma_px=sigma, rng=rng)]
                s = sigma if sigma > 0 else None
                pairs = [grid_vanishing_points(g, sigma_px=s) for g in px]
                outline = [outline_vps(g) for g in px]
                for key, fn, arg in (
                    ("rect", lambda a: rectangle_intrinsics(a, SIZE, mc_samples=0).k, pairs),
                    ("sq", lambda a: rectangle_intrinsics(a, SIZE, square_pixels=True,
                                                          mc_samples=0).k, pairs),
                    ("outline", lambda a: rectangle_intrinsics(a, SIZE, mc_samples=0).k, outline),
                    ("zhang", lambda a: zhang_intrinsics([fit_homography(
                        plane, g.reshape(-1, 2)) for g in a]), px),
                ):
                    try:
                        e[key].append(err_pct(fn(arg)))
                    except DegenerateError:
                        pass
            ratio = (np.median(e["rect"]) / np.median(e["zhang"])
                     if sigma > 0 and e["zhang"] else float("nan"))
            print(f"| {sigma:g} | {n} | {fmt(e['rect'], trials)} | {fmt(e['sq'], trials)} | "
                  f"{fmt(e['outline'], trials)} | {fmt(e['zhang'], trials)} | {ratio:.2f} |")


def seed004(trials: int, rng: np.random.Generator) -> None:
    """General-motion self-calibration: the paper's linear K and the ML refinement."""
    boards = two_board_scene()
    t = normalizer(SIZE)
    print("\n## General-motion self-calibration (err %, median (max))")
    print("paper: exact without noise; more images -> more stable; Cholesky of K K^T can "
          "fail on noisy data")
    print("| sigma px | images | linear (paper) | Cholesky failures | ML refined | "
          "rotation-only method on the same data [k/n: runs with a positive-definite K K^T] |")
    print("|---|---|---|---|---|---|")
    for sigma in NOISE:
        for n in (3, 4, 6, 10):
            lin, ref, rot, fails = [], [], [], 0
            for _ in range(trials):
                views = general_motion_views(CAM, boards, n, rng)
                px = board_pixels(CAM, boards, views, sigma_px=sigma, rng=rng)
                s = sigma if sigma > 0 else None
                tracks = [[vp for g in img for vp in grid_vanishing_points(g, sigma_px=s)]
                          for img in px]
                try:
                    lin.append(err_pct(linear_selfcal(np.array([[p.p for p in tr]
                                                                for tr in tracks]), t)))
                except NotPositiveDefiniteError:
                    fails += 1
                try:
                    ref.append(err_pct(selfcal_intrinsics(tracks, SIZE, mc_samples=0).k))
                except DegenerateError:
                    pass
                hs = [fit_homography(boards[0].corners()[..., :2].reshape(-1, 2),
                                     img[0].reshape(-1, 2)) for img in px]
                try:
                    rot.append(err_pct(rotation_intrinsics(interview_homographies(hs))))
                except DegenerateError:
                    pass
            print(f"| {sigma:g} | {n} | {fmt(lin, trials)} | {fails}/{trials} | "
                  f"{fmt(ref, trials)} | {fmt(rot, trials)} |")


def rotation_only(trials: int, rng: np.random.Generator) -> None:
    """Hartley's rotation-only method on pan-tilt data (plane homographies from corners)."""
    board = two_board_scene()[0]
    print("\n## Rotation-only (Hartley, pan-tilt rigs) on its own data (err %, median (max); "
          "rotations 3-12 deg, [k/n]: runs with a positive-definite K K^T)")
    print("| sigma px | images | rotation-only |")
    print("|---|---|---|")
    obj = board.corners()[..., :2].reshape(-1, 2)
    for sigma in NOISE:
        for n in (3, 5, 10):
            errs = []
            for _ in range(trials):
                rv = general_motion_views(CAM, [board], 1, rng)[0]
                hs = []
                for _ in range(n):
                    ax = rng.normal(size=3)
                    ang = np.radians(rng.uniform(3, 12))
                    q = _rot(ax, ang) if hs else np.eye(3)
                    uv = CAM.project(board.corners().reshape(-1, 3) @ (q @ rv.rotation).T
                                     + q @ rv.translation)
                    if not np.all(np.isfinite(uv)):
                        continue
                    hs.append(fit_homography(obj, uv + sigma * rng.standard_normal(uv.shape)))
                try:
                    errs.append(err_pct(rotation_intrinsics(interview_homographies(hs))))
                except DegenerateError:
                    pass
            print(f"| {sigma:g} | {n} | {fmt(errs, trials)} |")


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation about `axis` by `angle` rad."""
    import cv2

    return cv2.Rodrigues(axis / np.linalg.norm(axis) * angle)[0]


def seed003(trials: int, rng: np.random.Generator) -> None:
    """Robust estimation at gross outlier rates; non-planar PnP vs noise."""
    print("\n## RANSAC inlier recall vs outlier rate (mean over trials)")
    print("| outliers | adaptive RANSAC H: recall, samples (theory) | USAC MAGSAC++ H: recall "
          "| adaptive RANSAC DLT: recall, samples (theory) |")
    print("|---|---|---|---|")
    k = CAM.camera_matrix
    for frac in (0.2, 0.4, 0.6):
        old, new, dlt, drawn, h_drawn = [], [], [], [], []
        for _ in range(trials):
            src = rng.uniform(0, 500, (400, 2))
            h = np.array([[1.1, 0.05, 20], [0.02, 0.95, -10], [1e-4, -5e-5, 1]])
            q = np.c_[src, np.ones(400)] @ h.T
            dst = q[:, :2] / q[:, 2:] + 0.3 * rng.standard_normal((400, 2))
            out = rng.random(400) < frac
            dst[out] = rng.uniform(0, 600, (int(out.sum()), 2))
            st_h: dict[str, float] = {}
            old.append(ransac_homography(src, dst, 1.0, rng, stats=st_h)[1][~out].mean())
            h_drawn.append(st_h["samples"])
            new.append(usac_homography(src, dst, 1.0)[1][~out].mean())
            x = rng.uniform(-150, 150, (400, 3))
            p = (x + np.array([0, 0, 600.0])) @ k.T
            u = p[:, :2] / p[:, 2:] + 0.3 * rng.standard_normal((400, 2))
            u[out] = rng.uniform(0, 640, (int(out.sum()), 2))
            try:
                st: dict[str, float] = {}
                inl = ransac_dlt(x, u, 1.0, rng, stats=st)[1]
                dlt.append(inl[~out].mean())
                drawn.append(st["samples"])
            except DegenerateError:
                dlt.append(0.0)
        th4, th6 = (required_iterations(1 - frac, s, 0.999) for s in (4, 6))
        print(f"| {frac:.0%} | {np.mean(old):.3f}, {np.median(h_drawn):.0f} ({th4:.0f}) | "
              f"{np.mean(new):.3f} | {np.mean(dlt):.3f}, {np.median(drawn) if drawn else 0:.0f} "
              f"({th6:.0f}) |")
    print("\n## Non-planar PnP, rotation error (deg) vs pixel noise, 50 points")
    print("| sigma px | sqpnp | epnp | iterative |")
    print("|---|---|---|---|")
    for sigma in NOISE:
        row = {m: [] for m in ("sqpnp", "epnp", "iterative")}
        for _ in range(trials):
            r = _rot(rng.normal(size=3), rng.uniform(0, 0.5))
            x = rng.uniform(-150, 150, (50, 3))
            p = (x @ r.T + np.array([0, 0, 600.0])) @ k.T
            u = p[:, :2] / p[:, 2:] + sigma * rng.standard_normal((50, 2))
            for m in row:
                re, _, _ = solve_pnp(x, u, k, method=m)
                row[m].append(np.degrees(np.arccos(np.clip((np.trace(re.T @ r) - 1) / 2, -1, 1))))
        print(f"| {sigma:g} | " + " | ".join(f"{np.median(v):.2g}" for v in row.values()) + " |")


def white_flats(trials: int, rng: np.random.Generator) -> None:
    """Quick intrinsics from rendered white flats (sub-pixel quad edges), square pixels."""
    cam = PinholeCamera(640, 480, fx=520.0, fy=520.0, cx=331.0, cy=233.5)
    print("\n## Quick intrinsics from rendered white flats (screen 160x100 mm, 640x480, "
          "square-pixel camera), err % median (max)")
    print("| flats | rectangle square px | rectangle fx!=fy | MC std fx (px) |")
    print("|---|---|---|---|")
    for n in (4, 8):
        sq, gen, std = [], [], []
        for _ in range(trials):
            poses = whole_screen_poses(cam, DEFAULT_SCREEN, n, rng)
            pairs = [find_quads(white_flat_image(cam, p, DEFAULT_SCREEN, rng))[0]
                     .vanishing_points() for p in poses]
            e = rectangle_intrinsics(pairs, SIZE, square_pixels=True, mc_samples=100)
            sq.append(err_pct(e.k, cam))
            std.append(e.std["fx"])
            gen.append(err_pct(rectangle_intrinsics(pairs, SIZE, mc_samples=0).k, cam))
        print(f"| {n} | {np.median(sq):.3g} ({max(sq):.3g}) | {np.median(gen):.3g} "
              f"({max(gen):.3g}) | {np.median(std):.3g} |")


def main() -> None:
    """Run every table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--trials", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-flats", action="store_true", help="skip the rendered white flats")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    seed002(args.trials, rng)
    seed004(args.trials, rng)
    rotation_only(args.trials, rng)
    seed003(args.trials, rng)
    if not args.no_flats:
        white_flats(max(args.trials // 5, 2), rng)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
