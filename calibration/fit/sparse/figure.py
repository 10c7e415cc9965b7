"""The uncertainty figure of a fit to target observations: where the model is known well
(projection 1-sigma over the sensor, the observed points on top) and, with
cross-validation, how far two fits of disjoint views differ across the image."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calibration.figures import one_at_a_time, subplots
from calibration.fit.result import CalibrationResult


@one_at_a_time
def write_uncertainty_png(result: CalibrationResult, path: str | Path) -> None:
    """One or two sensor maps (px): projection sigma, and the cross-validation difference."""
    stats = result.stats
    if "projection_sigma_px" not in stats:
        raise ValueError("uncertainty figure: the result is not a fit to target observations")
    cv = stats.get("cross_validation")
    fig, axes = subplots(2 if cv else 1, (14 if cv else 7.2, 4.8))
    axes = np.atleast_1d(axes)
    w, h = result.model.image_size
    sig = np.array(stats["projection_sigma_px"]["values"], dtype=float)
    ax = axes[0]
    top = float(np.nanpercentile(sig, 95)) if np.isfinite(sig).any() else 1.0
    im = ax.imshow(sig, extent=(0, w, h, 0), vmin=0, vmax=top, cmap="viridis",
                   interpolation="bilinear")
    fig.colorbar(im, ax=ax, label="projection 1-sigma (px)")
    pts = np.concatenate([result.residual_pixels[k] for k in sorted(result.residual_pixels)])
    ax.plot(pts[:, 0], pts[:, 1], ".", color="white", markersize=1.5, alpha=0.6)
    ax.set(xlim=(0, w), ylim=(h, 0), aspect="equal",
           title=f"projection 1-sigma, frame rotation removed: median "
                 f"{stats['projection_sigma_px']['median']:.3g} px")
    if cv:
        pair = max(cv["pairs"], key=lambda p: p["ratio"])
        diff = np.array(pair["difference_px"], dtype=float)
        ax = axes[1]
        im = ax.imshow(diff, extent=(0, w, h, 0), vmin=0, cmap="viridis",
                       vmax=float(np.nanpercentile(diff, 95)) if np.isfinite(diff).any() else 1,
                       interpolation="bilinear")
        fig.colorbar(im, ax=ax, label="|difference| (px)")
        ax.set(xlim=(0, w), ylim=(h, 0), aspect="equal",
               title=f"two view sets differ: RMS {pair['rms_difference_px']:.3g} px, "
                     f"predicted {pair['rms_predicted_px']:.3g} -> {cv['verdict']}")
    fig.suptitle(f"{result.model.type_name}: {len(result.poses)} views, RMS "
                 f"{stats['rms_px']:.4g} px, sigma {stats['sigma_px']:.3g} px")
    fig.tight_layout()
    fig.savefig(str(path), dpi=90)
