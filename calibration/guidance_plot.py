"""The next-pose picture: predicted ray-sigma maps now and after the suggested pose, with the
screen's outline where the camera would see it."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
from matplotlib.colors import LogNorm

from calibration.figures import one_at_a_time, subplots

_DPI = 100


def _norm(values: np.ndarray) -> LogNorm:
    """Log colour scale over the finite positive values (uncertainty spans decades)."""
    pos = values[np.isfinite(values) & (values > 0)]
    if not pos.size:
        return LogNorm(1e-3, 1.0)
    lo, hi = float(pos.min()), float(pos.max())
    return LogNorm(lo, max(hi, lo * 1.01))


def _ticks(norm: LogNorm, count: int = 5) -> list[float]:
    """Tick values from the low end to the high end, both ends labelled (a log scale's own
    ticks fall on decades and can leave the low end without a number)."""
    lo, hi = float(norm.vmin), float(norm.vmax)
    inner = [float(f"{v:.2g}") for v in np.geomspace(lo, hi, count)[1:-1]]
    return [lo, *(v for v in inner if lo < v < hi), hi]


@one_at_a_time
def guidance_png(before: np.ndarray, after: np.ndarray, outline: np.ndarray,
                 image_size: tuple[int, int], title: str, path: Path) -> None:
    """Predicted ray-sigma maps (rad, nan where not predicted) now and after the suggested
    pose, on one labelled colour scale (urad), with its screen outline (camera px)."""
    w, h = image_size
    fig, axes = subplots(2, (12, 4.4))
    norm = _norm(np.concatenate([before.ravel(), after.ravel()]) * 1e6)
    for ax, img, name in ((axes[0], before, "now"), (axes[1], after, "after the suggested pose")):
        im = ax.imshow(img * 1e6, extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap="inferno",
                       norm=norm, interpolation="bilinear")
        ax.set(aspect="equal", xlim=(-0.5, w - 0.5), ylim=(h - 0.5, -0.5),
               xlabel="u (camera px)", ylabel="v (camera px)")
        ax.set_facecolor("#bbbbbb")
        ax.set_title(f"predicted ray 1-sigma {name}\nworst {np.nanmax(img) * 1e6:.3g} urad "
                     "(grey: beyond 70 deg from the axis)", fontsize=9)
        bar = fig.colorbar(im, ax=ax, label="ray direction 1-sigma (urad, log scale)")
        ticks = _ticks(norm)
        bar.set_ticks(ticks, labels=[f"{t:.3g}" for t in ticks])
        bar.minorticks_off()
    closed = np.vstack([outline, outline[:1]])
    axes[1].plot(closed[:, 0], closed[:, 1], "c-", lw=2, label="suggested screen")
    axes[1].legend(loc="lower right", fontsize=8)
    fig.suptitle("\n".join(textwrap.wrap(title, 110)), fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.92))
    fig.savefig(str(path), dpi=_DPI, bbox_inches="tight")
