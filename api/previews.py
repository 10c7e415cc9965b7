"""PNG previews of decoded maps (x, y, sigma, mask), each with a colour bar and its units."""

from __future__ import annotations

import io

import numpy as np
from matplotlib.colors import ListedColormap, LogNorm, Normalize

from calibration import one_at_a_time, subplots
from calibration.shared.maps import DecodedMaps

PREVIEW_KINDS = ("x", "y", "sigma", "mask")
_LABELS = {"x": "decoded screen x (screen px)", "y": "decoded screen y (screen px)",
           "sigma": "decoded 1-sigma |(sx, sy)| (screen px, log scale)"}


@one_at_a_time
def preview_png(maps: DecodedMaps, kind: str) -> bytes:
    """Colour-mapped PNG of one map with its colour bar; invalid pixels are grey."""
    if kind not in PREVIEW_KINDS:
        raise ValueError(f"preview kind {kind!r}: expected one of {PREVIEW_KINDS}")
    h, w = maps.mask.shape
    fig, ax = subplots(1, (6.4, 6.4 * h / w * 0.85 + 0.6))
    ax.set_facecolor("#888888")
    if kind == "mask":
        im = ax.imshow(maps.mask.astype(float), cmap=ListedColormap(["black", "white"]),
                       vmin=0, vmax=1, interpolation="nearest")
        bar = fig.colorbar(im, ax=ax, ticks=[0.25, 0.75])
        bar.ax.set_yticklabels(["not decoded", "decoded"])
        title = f"mask: {int(maps.mask.sum())} valid pixels"
    else:
        if kind == "sigma":
            values = np.hypot(maps.sigma_x, maps.sigma_y).astype(np.float64)
        else:
            values = maps.x if kind == "x" else maps.y
        good = maps.mask & np.isfinite(values) & ((values > 0) if kind == "sigma" else True)
        shown = np.where(good, values, np.nan)
        norm = None
        if good.any():
            lo, hi = np.percentile(values[good], [1, 99])
            hi = max(float(hi), float(lo) * 1.001 + 1e-12)
            norm = LogNorm(lo, hi) if kind == "sigma" else Normalize(lo, hi)
        im = ax.imshow(shown, cmap="viridis", norm=norm, interpolation="nearest")
        fig.colorbar(im, ax=ax, label=_LABELS[kind])
        title = f"{kind} map (grey: not decoded)"
    ax.set(title=title, xlabel="u (camera px)", ylabel="v (camera px)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    return buf.getvalue()
