"""Passive targets: detection and the pixel-space fit on OpenCV's real sample chessboard
images (left and right camera, every image the detector accepts) and on simulated boards
with a known bow (hw_mocks.board, detected by phasecal's detector).

Prints, per data set: views, RMS, sigma, outliers, each intrinsic with its 1-sigma beside
`cv2.calibrateCameraExtended`'s on the same corners (real images) or the truth (simulated),
the fitted bow, the cross-validation verdict, and wall and CPU seconds of detection and fit;
then the same for the generic model sgcc (bow fitted, cross-validated): its RMS beside
opencv5's, its mesh, its cross-validation and, on simulated boards, its rays against the
truth camera's (normalized by the fit's predicted projection covariance).

    .venv/bin/python benchmarks/targets.py [--seeds 3]

The real images come from `make setup` (scripts/fetch-opencv-samples.sh).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from calibration import TargetSpec, calibrate_observations, detect_file
from calibration.fit.sparse.uncertainty import projection_covariance
from calibration.targets.detect import detect_image
from hw_mocks.board import BoardRenderer, BoardTruth, look_at_poses
from hw_mocks.cameras import mild_pinhole

SAMPLES = Path(__file__).resolve().parents[1] / "data" / "opencv-samples"
NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


class Clock:
    """Wall and CPU seconds since the last lap."""

    def __init__(self) -> None:
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def lap(self) -> tuple[float, float]:
        w, c = time.perf_counter(), time.process_time()
        out = (w - self.wall, c - self.cpu)
        self.wall, self.cpu = w, c
        return out


def truth_ratio(cam, result, views: list) -> tuple[float, float]:
    """sgcc's rays against the truth camera's at the observed pixels, after the rotation
    that best aligns the frames: (sqrt(mean z^2 / 2) with the fit's projection covariance,
    RMS pixel difference)."""
    pix = np.concatenate([v.image_xy for v in views])
    _, truth = cam.rays(pix[:, 0], pix[:, 1])
    _, model = result.model.unproject(pix)
    u, _, vt = np.linalg.svd(model.T @ truth)
    rays = 1000.0 * truth @ (u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt).T
    diff = result.model.project(rays) - pix
    cov = projection_covariance(result.model, result.model.covariance, rays)
    z2 = np.einsum("ni,nij,nj->n", diff, np.linalg.inv(cov), diff)
    return float(np.sqrt(np.mean(z2) / 2)), float(np.sqrt(np.mean(np.sum(diff**2, axis=1))))


def sgcc_and_print(views: list, parametric_rms: float, cam=None) -> None:
    """The generic model on the same views: RMS, mesh, cross-validation, truth, time."""
    clock = Clock()
    fit = calibrate_observations(views, "sgcc", options={"target": "fit"},
                                 cross_validate_folds=2)
    wall, cpu = clock.lap()
    st = fit.stats
    mesh = st["mesh"]["candidates"][-1]
    cv = st["cross_validation"]
    pair = cv["pairs"][0]
    print(f"\nsgcc, bow fitted: RMS {st['rms_px']:.4f} px (opencv5 {parametric_rms:.4f}), mesh "
          f"{mesh['cells'][0]}x{mesh['cells'][1]} ({mesh['points_per_cell']:.1f} points per "
          f"cell), {st['outliers']} outliers; projection 1-sigma median "
          f"{st['projection_sigma_px']['median']:.3f} px")
    print(f"sgcc cross-validation: RMS difference {pair['rms_difference_px']:.3f} px, predicted "
          f"{pair['rms_predicted_px']:.3f} px, ratio {cv['ratio']:.2f} -> {cv['verdict']}; "
          f"fit + cross-validation {wall:.2f} s wall / {cpu:.2f} s CPU")
    if cam is not None:
        ratio, rms = truth_ratio(cam, fit, views)
        print(f"sgcc rays against the truth at the observed pixels: RMS {rms:.4f} px, "
              f"normalized ratio {ratio:.2f}")


def fit_and_print(label: str, views: list, reference: dict[str, tuple[float, float]],
                  ref_name: str, detect_s: tuple[float, float], truth_bow=None,
                  cam=None) -> None:
    clock = Clock()
    flat = calibrate_observations(views, "opencv5", options={"weights": "equal"})
    fit = calibrate_observations(views, "opencv5", options={"target": "fit"},
                                 cross_validate_folds=2)
    fit_s = clock.lap()
    st, fst = fit.stats, flat.stats
    print(f"\n### {label}: {len(views)} views, {sum(p['n_points'] for p in st['per_pose'])} "
          f"corners")
    print(f"detect {detect_s[0]:.2f} s wall / {detect_s[1]:.2f} s CPU; both fits and the "
          f"cross-validation {fit_s[0]:.2f} s wall / {fit_s[1]:.2f} s CPU")
    print(f"flat, equal weights: RMS {fst['rms_px']:.4f} px, {fst['outliers']} outliers")
    print(f"bow fitted, observed weights: RMS {st['rms_px']:.4f} px, sigma "
          f"{st['sigma_px']:.4f} px, {st['outliers']} outliers")
    print(f"\n| param | phasecal flat, equal w. | {ref_name} | diff/sigma | "
          f"phasecal bow fit | diff/sigma |")
    print("|---|---|---|---|---|---|")
    for i, n in enumerate(NAMES):
        v, s = flat.model.get_params()[i], fst["param_std"][n]
        rv, rs = reference[n]
        bv, bs = fit.model.get_params()[i], st["param_std"][n]
        ref = f"{rv:.6g} +- {rs:.2g}" if rs else f"{rv:.6g}"
        print(f"| {n} | {v:.6g} +- {s:.2g} | {ref} | {(v - rv) / s:+.3f} | "
              f"{bv:.6g} +- {bs:.2g} | {(bv - rv) / bs:+.2f} |")
    t = st["target"]
    bow = (f"bow x {t['bow_x_mm']:+.4f} +- {t['bow_x_std_mm']:.4f} mm, y "
           f"{t['bow_y_mm']:+.4f} +- {t['bow_y_std_mm']:.4f} mm")
    if truth_bow is not None:
        bow += (f" (truth {truth_bow[0]:+.3f}, {truth_bow[1]:+.3f}: "
                f"{(t['bow_x_mm'] - truth_bow[0]) / t['bow_x_std_mm']:+.2f}, "
                f"{(t['bow_y_mm'] - truth_bow[1]) / t['bow_y_std_mm']:+.2f} sigma)")
    cv = st["cross_validation"]
    pair = cv["pairs"][0]
    print(f"\n{bow}; projection 1-sigma median {st['projection_sigma_px']['median']:.3f} px")
    print(f"cross-validation (views {cv['folds'][0]} | {cv['folds'][1]}): RMS difference "
          f"{pair['rms_difference_px']:.3f} px, predicted {pair['rms_predicted_px']:.3f} px, "
          f"ratio {cv['ratio']:.2f} -> {cv['verdict']}")
    sgcc_and_print(views, st["rms_px"], cam)


def real(side: str) -> None:
    files = sorted(SAMPLES.glob(f"{side}[0-9][0-9].jpg"))
    if not files:
        sys.exit(f"no images in {SAMPLES}: run `make setup`")
    spec = TargetSpec.parse("chessboard:9x6:25")
    clock = Clock()
    found = [detect_file(f, spec) for f in files]
    detect_s = clock.lap()
    views = [d.observations for d in found if d.observations is not None]
    obj = [v.target_xyz.astype(np.float32) for v in views]
    img = [v.image_xy.astype(np.float32) for v in views]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 500, 1e-16)
    rms, k, d, _, _, std, *_ = cv2.calibrateCameraExtended(obj, img, views[0].image_size,
                                                           None, None, criteria=crit)
    vals = [k[0, 0], k[1, 1], k[0, 2], k[1, 2], *np.ravel(d)[:5]]
    ref = {n: (float(v), float(s)) for n, v, s in zip(NAMES, vals, np.ravel(std)[:9],
                                                      strict=True)}
    print(f"\n## OpenCV sample {side} ({len(views)}/{len(files)} images detected); "
          f"cv2.calibrateCamera RMS {rms:.6f} px")
    fit_and_print(f"real {side}", views, ref, "cv2.calibrateCameraExtended", detect_s)


def simulated(seed: int) -> None:
    cam = mild_pinhole()
    board = BoardTruth(9, 6, 20.0, bow_x_mm=1.5, bow_y_mm=-0.8)
    spec = TargetSpec.parse("chessboard:9x6:20")
    clock = Clock()
    renderer = BoardRenderer(cam)
    images = [renderer.render(board, p, blur_px=1.0, seed=100 * seed + k)
              for k, p in enumerate(look_at_poses(board, 10, 420.0, seed=seed))]
    render_s = clock.lap()
    found = [detect_image(im, spec, source=f"sim{k}") for k, im in enumerate(images)]
    detect_s = clock.lap()
    views = [d.observations for d in found if d.observations is not None]
    truth = [cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist]
    ref = {n: (float(v), 0.0) for n, v in zip(NAMES, truth, strict=True)}
    print(f"\n## simulated board, seed {seed} (render {render_s[1]:.2f} s CPU)")
    fit_and_print(f"simulated seed {seed}", views, ref, "truth", detect_s,
                  (board.bow_x_mm, board.bow_y_mm), cam)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=3, help="simulated sessions")
    args = parser.parse_args()
    for side in ("left", "right"):
        real(side)
    for seed in range(args.seeds):
        simulated(seed)


if __name__ == "__main__":
    main()
