"""Residual plot PNG (matplotlib Agg): vectors, magnitude map and radial profile of a fit.

A wrong model shows as a systematic, radially growing pattern in the map and a rising
radial profile far above the expected noise-floor line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.figures import one_at_a_time, subplots
from calibration.fit.result import CalibrationResult
from calibration.models.parametric import PinholeFamily

_QUIVER_POINTS = 1500
_POINTS_PER_BIN = 4  # magnitude map: about this many residuals per bin


def binned_rms(pix: np.ndarray, mag: np.ndarray, w: int, h: int) -> np.ndarray:
    """RMS of `mag` at pixels `pix` (N, 2) on square bins over a `w` x `h` image, sized for
    about 4 points each; NaN where a bin is empty. The magnitude map of every residual plot:
    an image draws in milliseconds where a per-point scatter of a dense fit took seconds."""
    side = max(1.0, float(np.sqrt(w * h * _POINTS_PER_BIN / max(len(mag), 1))))
    nx, ny = max(1, int(np.ceil(w / side))), max(1, int(np.ceil(h / side)))
    ix = np.clip((pix[:, 0] / side).astype(int), 0, nx - 1)
    iy = np.clip((pix[:, 1] / side).astype(int), 0, ny - 1)
    flat = iy * nx + ix
    count = np.bincount(flat, minlength=nx * ny)
    total = np.bincount(flat, weights=mag**2, minlength=nx * ny)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(total / count).reshape(ny, nx)  # 0/0 -> NaN: drawn blank


@one_at_a_time
def write_residual_report(result: CalibrationResult, path: str | Path) -> None:
    """Save a 3-panel PNG of all training-pose residuals (camera px)."""
    if not result.residuals:
        raise ValueError("report: the result holds no residuals to plot")
    order = sorted(result.residuals)
    pix = np.concatenate([result.residual_pixels[i] for i in order])
    res = np.concatenate([result.residuals[i] for i in order])
    expected_of = {p["pose"]: p.get("expected_rms_px") for p in result.stats.get("per_pose", [])}
    exp = np.concatenate([np.full(len(result.residuals[i]), expected_of.get(i) or np.nan)
                          for i in order])
    ok = np.all(np.isfinite(res), axis=1)
    pix, res, exp = pix[ok], res[ok], exp[ok]
    mag = np.linalg.norm(res, axis=1)
    w, h = result.model.image_size
    stats = result.stats
    fig, axes = subplots(3, (16, 4.8))
    step = max(1, pix.shape[0] // _QUIVER_POINTS)
    ax = axes[0]
    ax.quiver(pix[::step, 0], pix[::step, 1], res[::step, 0], -res[::step, 1], mag[::step],
              angles="xy", cmap="viridis")
    ax.set(xlim=(0, w), ylim=(h, 0), aspect="equal", title="residual vectors (camera px)")
    ax = axes[1]
    hi = float(np.percentile(mag, 99)) if mag.size else 1.0
    im = ax.imshow(binned_rms(pix, mag, w, h), extent=(0, w, h, 0), vmin=0, vmax=hi,
                   cmap="magma", interpolation="nearest")
    fig.colorbar(im, ax=ax, label="RMS |residual| px")
    ax.set(xlim=(0, w), ylim=(h, 0), aspect="equal", title="residual magnitude (binned RMS)")
    ax = axes[2]
    cam = result.model
    center = (cam.cx, cam.cy) if isinstance(cam, PinholeFamily) else ((w - 1) / 2, (h - 1) / 2)
    rad = np.hypot(pix[:, 0] - center[0], pix[:, 1] - center[1])
    edges = np.linspace(0, max(float(rad.max(initial=1.0)), 1.0), 21)
    idx = np.clip(np.digitize(rad, edges) - 1, 0, 19)
    cnt = np.bincount(idx, minlength=20)
    rms = np.sqrt(np.bincount(idx, weights=mag**2, minlength=20) / np.maximum(cnt, 1))
    mids = 0.5 * (edges[1:] + edges[:-1])
    ax.plot(mids[cnt > 0], rms[cnt > 0], "o-", label="RMS residual")
    # Each point's own expected noise (its pose's noise floor), binned like the residuals:
    # wide-angle edges are expected to be noisier, so one global line would mislead.
    has = np.isfinite(exp)
    ecnt = np.bincount(idx[has], minlength=20)
    erms = np.sqrt(np.bincount(idx[has], weights=exp[has] ** 2, minlength=20)
                   / np.maximum(ecnt, 1))
    if has.any():
        ax.plot(mids[ecnt > 0], erms[ecnt > 0], "r--", label="expected (noise floor)")
    ax.set(xlabel="radius from principal point / image center (px)", ylabel="RMS |residual| (px)",
           title="radial residual profile")
    ax.legend()
    flag = "OK" if stats.get("model_adequate") else "MODEL INADEQUATE"
    screen = stats.get("noise_floor_ratio_screen")  # only a screen's maps have a screen plane
    fig.suptitle(f"{result.model.type_name}: RMS {stats.get('rms_px', float('nan')):.4g} px, "
                 f"noise floor {stats.get('expected_rms_px', float('nan')):.4g} px, "
                 f"ratio {stats.get('noise_floor_ratio', float('nan')):.3g}"
                 + (f" (screen plane {screen:.3g})" if screen is not None
                    and np.isfinite(screen) else "") + f" -> {flag}")
    fig.tight_layout()
    fig.savefig(str(path), dpi=90)
