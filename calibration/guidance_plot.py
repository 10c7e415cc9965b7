"""The next-pose pictures: predicted ray-sigma maps now and after the suggested pose, with the
screen's outline where the camera would see it; on a rig, one picture per camera (cameras of
different resolutions each keep their own aspect), all on the rig's one colour scale."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

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


def _sigma_panel(fig: Figure, ax: Axes, img: np.ndarray, norm: LogNorm,
                 image_size: tuple[int, int], heading: str) -> None:
    """One ray-sigma map (rad) in camera pixels with its labelled log colour bar (urad)."""
    w, h = image_size
    im = ax.imshow(img * 1e6, extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap="inferno",
                   norm=norm, interpolation="bilinear")
    ax.set(aspect="equal", xlim=(-0.5, w - 0.5), ylim=(h - 0.5, -0.5),
           xlabel="u (camera px)", ylabel="v (camera px)")
    ax.set_facecolor("#bbbbbb")
    ax.set_title(heading, fontsize=9)
    bar = fig.colorbar(im, ax=ax, label="ray direction 1-sigma (urad, log scale)")
    ticks = _ticks(norm)
    bar.set_ticks(ticks, labels=[f"{t:.3g}" for t in ticks])
    bar.minorticks_off()


def _outline(ax: Axes, outline: np.ndarray) -> None:
    """The suggested screen's border, closed, with its legend entry."""
    closed = np.vstack([outline, outline[:1]])
    ax.plot(closed[:, 0], closed[:, 1], "c-", lw=2, label="suggested screen")
    ax.legend(loc="lower right", fontsize=8)


@one_at_a_time
def guidance_png(before: np.ndarray, after: np.ndarray, outline: np.ndarray,
                 image_size: tuple[int, int], title: str, path: Path) -> None:
    """Predicted ray-sigma maps (rad, nan where not predicted) now and after the suggested
    pose, on one labelled colour scale (urad), with its screen outline (camera px)."""
    fig, axes = subplots(2, (12, 4.4))
    norm = _norm(np.concatenate([before.ravel(), after.ravel()]) * 1e6)
    for ax, img, name in ((axes[0], before, "now"), (axes[1], after, "after the suggested pose")):
        _sigma_panel(fig, ax, img, norm, image_size,
                     f"predicted ray 1-sigma {name}\nworst {np.nanmax(img) * 1e6:.3g} urad "
                     "(grey: beyond 70 deg from the axis)")
    _outline(axes[1], outline)
    fig.suptitle("\n".join(textwrap.wrap(title, 110)), fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.92))
    fig.savefig(str(path), dpi=_DPI, bbox_inches="tight")


def rig_sigma_range(maps: list[np.ndarray]) -> tuple[float, float]:
    """The one colour range (urad) of a rig's pictures, so cameras compare at a glance."""
    norm = _norm(np.concatenate([m.ravel() for m in maps]) * 1e6)
    return float(norm.vmin), float(norm.vmax)


@one_at_a_time
def rig_camera_guidance_png(before: np.ndarray, outline: np.ndarray | None,
                            image_size: tuple[int, int], sigma_range: tuple[float, float],
                            title: str, detail: str, path: Path) -> None:
    """One camera of a rig: its predicted ray-sigma map now (rad, nan where not predicted) on
    the rig's colour range (`rig_sigma_range`, urad), with the suggested screen's border in
    its pixels when the pose serves it (`outline` None: it does not see the screen)."""
    w, h = image_size
    map_w = min(5.0, 3.8 * w / h)  # inches: a wide or a tall sensor fits the same box
    width = max(map_w + 1.6, 4.4)
    fig, ax = subplots(1, (width, map_w * h / w + 1.4))
    _sigma_panel(fig, ax, before, LogNorm(*sigma_range), image_size,
                 f"predicted ray 1-sigma now: {detail}\n(grey: beyond 70 deg from the axis)")
    if outline is not None:
        _outline(ax, outline)
    fig.suptitle("\n".join(textwrap.wrap(title, int(9 * width))), fontsize=10,
                 fontweight="bold")
    fig.tight_layout()
    fig.savefig(str(path), dpi=_DPI, bbox_inches="tight")
