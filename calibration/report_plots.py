"""The PNGs of the calibration report (matplotlib Agg), each drawn from `ReportData`.

Every figure carries its scale: colour bars on maps, a reference arrow on vector fields,
the expected distribution on histograms, each point's expected noise on the radial profile.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.cm import ScalarMappable
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from calibration.figures import one_at_a_time, subplots
from calibration.report import binned_rms
from calibration.report_data import PoseView, ReportData, poses_per_pixel, whitened

_QUIVER_POINTS = 900
_DPI = 80


def _nice(value: float) -> float:
    """A round number (1, 2 or 5 times a power of ten) close to `value`."""
    if not np.isfinite(value) or value <= 0:
        return 1.0
    exp = np.floor(np.log10(value))
    return float(min((1, 2, 5, 10), key=lambda m: abs(m * 10**exp - value)) * 10**exp)


def _log_norm(finite: np.ndarray) -> LogNorm:
    """Log colour scale over the values: uncertainty spans decades from the data to the
    extrapolated corners, which a linear scale would paint one colour."""
    pos = finite[finite > 0]
    if not pos.size:
        return LogNorm(1e-3, 1.0)
    lo, hi = float(np.percentile(pos, 1)), float(pos.max())
    return LogNorm(lo, max(hi, lo * 1.01))


def colour_bar(fig: Figure, image: ScalarMappable, ax: Axes, label: str,
               ticks: int = 5) -> None:
    """A colour bar whose ends are both labelled with their values: a log scale's default
    ticks fall on decades and can leave the low end of the bar without a number."""
    bar = fig.colorbar(image, ax=ax, label=label)
    lo, hi = float(image.norm.vmin), float(image.norm.vmax)
    if isinstance(image.norm, LogNorm):
        values = np.geomspace(lo, hi, ticks)
        bar.ax.minorticks_off()
    else:
        values = np.linspace(lo, hi, ticks)
    bar.set_ticks(values)
    bar.set_ticklabels([f"{v:.3g}" for v in values])


def _save(fig: Figure, path: Path) -> None:
    fig.tight_layout(rect=(0, 0, 1, 0.94) if fig.get_suptitle() else (0, 0, 1, 1))
    fig.savefig(str(path), dpi=_DPI, bbox_inches="tight")


@one_at_a_time
def pose_png(view: PoseView, image_size: tuple[int, int], path: Path) -> None:
    """Residual vectors (with a reference arrow) and binned magnitude map of one pose."""
    w, h = image_size
    ok = np.all(np.isfinite(view.residuals), axis=1)
    pix, res = view.pixels[ok], view.residuals[ok]
    mag = np.linalg.norm(res, axis=1)
    fig, axes = subplots(2, (12, 4.6))
    ref = _nice(float(np.percentile(mag, 90)) if mag.size else 1.0)
    gain = 0.04 * w / ref  # the reference residual is drawn 4% of the image width long
    step = max(1, len(pix) // _QUIVER_POINTS)
    ax = axes[0]
    q = ax.quiver(pix[::step, 0], pix[::step, 1], gain * res[::step, 0], gain * res[::step, 1],
                  mag[::step], angles="xy", scale_units="xy", scale=1.0, cmap="viridis",
                  width=0.003)
    ax.quiverkey(q, 0.80, 1.04, gain * ref, f"{ref:g} px (arrows x{gain:.3g})", labelpos="E",
                 coordinates="axes")
    ax.set(xlim=(0, w), ylim=(h, 0), aspect="equal", xlabel="u (px)", ylabel="v (px)")
    ax.set_title("residual vectors", loc="left")
    ax = axes[1]
    hi = float(np.percentile(mag, 99)) if mag.size else 1.0
    im = ax.imshow(binned_rms(pix, mag, w, h), extent=(0, w, h, 0), vmin=0, vmax=hi,
                   cmap="magma", interpolation="nearest")
    colour_bar(fig, im, ax, "RMS |residual| (camera px)")
    ax.set(xlim=(0, w), ylim=(h, 0), aspect="equal", title="residual magnitude (binned RMS)",
           xlabel="u (px)", ylabel="v (px)")
    kind = "held-out" if view.heldout else "training"
    st = view.stats
    fig.suptitle(f"{view.label} ({kind}): RMS {st['rms_px']:.4g} px, expected "
                 f"{st['expected_rms_px']:.4g} px, ratio {st['noise_floor_ratio']:.3g}, "
                 f"{st['n_points']} points")
    _save(fig, path)


@one_at_a_time
def histogram_png(views: list[PoseView], path: Path) -> None:
    """Whitened residual components against N(0,1), and |residual| against its expectation."""
    train = [v for v in views if not v.heldout]
    z = np.concatenate([whitened(v) for v in train]).ravel()
    z = z[np.isfinite(z)]
    fig, axes = subplots(2, (12, 4.2))
    ax = axes[0]
    lim = max(4.0, float(np.percentile(np.abs(z), 99.5)) if z.size else 4.0)
    bins = np.linspace(-lim, lim, 81)
    ax.hist(z, bins=bins, density=True, color="tab:blue", alpha=0.7,
            label="residual / expected sigma")
    xs = np.linspace(-lim, lim, 400)
    ax.plot(xs, np.exp(-xs**2 / 2) / np.sqrt(2 * np.pi), "r-", label="N(0, 1): expected noise")
    ax.set(xlabel="whitened residual component", ylabel="density",
           title=f"whitened residuals: std {np.std(z):.3g} (1 if the noise model holds)")
    ax.legend(fontsize=8)
    ax = axes[1]
    mag = np.concatenate([np.linalg.norm(v.residuals[v.inliers], axis=1) for v in train])
    rng = np.random.default_rng(0)
    cov = np.concatenate([v.expected_cov[v.inliers] for v in train])
    cov = cov[np.all(np.isfinite(cov), axis=(1, 2))]
    draws = np.einsum("nij,nj->ni", np.linalg.cholesky(cov + 1e-18 * np.eye(2)),
                      rng.standard_normal((len(cov), 2)))
    top = float(np.percentile(np.concatenate([mag, np.linalg.norm(draws, axis=1)]), 99.5))
    edges = np.linspace(0, top, 61)
    ax.hist(mag, bins=edges, density=True, alpha=0.7, label="|residual|")
    ax.hist(np.linalg.norm(draws, axis=1), bins=edges, density=True, histtype="step", color="r",
            lw=1.5, label="expected from each point's noise")
    ax.set(xlabel="|residual| (camera px)", ylabel="density", title="residual magnitude")
    ax.legend(fontsize=8)
    _save(fig, path)


@one_at_a_time
def radial_png(data: ReportData, path: Path) -> None:
    """RMS residual against radius, with the RMS of each point's own expected noise."""
    w, h = data.model.image_size
    cx = getattr(data.model, "cx", (w - 1) / 2)
    cy = getattr(data.model, "cy", (h - 1) / 2)
    fig, ax = subplots(1, (7, 4.2))
    for heldout, style, name in ((False, "o-", "training"), (True, "s-", "held-out")):
        vs = [v for v in data.poses if v.heldout == heldout]
        if not vs:
            continue
        pix = np.concatenate([v.pixels[v.inliers] for v in vs])
        mag2 = np.concatenate([np.sum(v.residuals[v.inliers] ** 2, axis=1) for v in vs])
        exp2 = np.concatenate([np.trace(v.expected_cov[v.inliers], axis1=1, axis2=2) for v in vs])
        rad = np.hypot(pix[:, 0] - cx, pix[:, 1] - cy)
        edges = np.linspace(0, max(float(rad.max(initial=1.0)), 1.0), 21)
        idx = np.clip(np.digitize(rad, edges) - 1, 0, 19)
        cnt = np.bincount(idx, minlength=20)
        mids = 0.5 * (edges[1:] + edges[:-1])[cnt > 0]
        rms = np.sqrt(np.bincount(idx, weights=mag2, minlength=20)[cnt > 0] / cnt[cnt > 0])
        erms = np.sqrt(np.bincount(idx, weights=exp2, minlength=20)[cnt > 0] / cnt[cnt > 0])
        ax.plot(mids, rms, style, label=f"RMS residual ({name})")
        ax.plot(mids, erms, "--", label=f"expected from each point's noise ({name})")
    ax.set(xlabel="radius from principal point / image centre (px)",
           ylabel="RMS |residual| (camera px)", title="radial residual profile")
    ax.legend(fontsize=8)
    _save(fig, path)


@one_at_a_time
def uncertainty_png(data: ReportData, path: Path) -> None:
    """Per-pixel 1-sigma ray direction uncertainty over the sensor, in microradians."""
    w, h = data.model.image_size
    img = (data.ray_sigma * 1e6).reshape(data.grid_shape)
    fig, ax = subplots(1, (7.5, 5))
    finite = img[np.isfinite(img)]
    im = ax.imshow(img, extent=(0, w, h, 0), cmap="inferno", norm=_log_norm(finite),
                   interpolation="bilinear")
    colour_bar(fig, im, ax, "ray direction 1-sigma (urad, log scale)")
    seen = poses_per_pixel(data) > 0
    ax.contour(seen.astype(float), levels=[0.5], colors="cyan", linewidths=1,
               extent=(0, w, 0, h), origin="upper")
    med = float(np.nanmedian(img)) if finite.size else float("nan")
    mx = float(np.nanmax(img)) if finite.size else float("nan")
    ax.set(aspect="equal", xlabel="u (px)", ylabel="v (px)",
           title=f"ray uncertainty: median {med:.3g} urad, max {mx:.3g} urad\n"
                 f"{data.ray_sigma_method}\ncyan line: edge of the training data")
    ax.title.set_fontsize(9)
    _save(fig, path)


@one_at_a_time
def coverage_png(data: ReportData, counts: np.ndarray, cell_kind: str, path: Path) -> None:
    """Observations per coverage cell (`report_data.coverage_counts`; empty cells red) and
    training poses per pixel."""
    w, h = data.model.image_size
    ny, nx = counts.shape
    views = poses_per_pixel(data)
    fig, axes = subplots(2, (12, 4.6))
    ax = axes[0]
    im = ax.imshow(np.where(counts > 0, counts, np.nan), extent=(0, w, h, 0), cmap="viridis",
                   interpolation="nearest", vmin=0, vmax=max(float(counts.max()), 1.0))
    colour_bar(fig, im, ax, "observations per cell (pixels x poses)")
    ax.set_facecolor("#d62728")
    empty = int(np.sum(counts == 0))
    ax.set(aspect="equal", xlabel="u (px)", ylabel="v (px)",
           title=f"coverage of {nx} x {ny} {cell_kind}: {empty} empty (red)")
    ax = axes[1]
    top = max(int(views.max()), 1)
    im = ax.imshow(views, extent=(0, w, h, 0), cmap="cividis", interpolation="nearest",
                   vmin=-0.5, vmax=top + 0.5)
    bar = fig.colorbar(im, ax=ax, label="training poses seeing the pixel")
    step = max(1, top // 8)
    bar.set_ticks(list(range(0, top + 1, step)))
    ax.set(aspect="equal", title="poses per pixel", xlabel="u (px)", ylabel="v (px)")
    _save(fig, path)


@one_at_a_time
def diff_png(pixels: np.ndarray, angle_rad: np.ndarray, image_size: tuple[int, int],
             step: float, title: str, path: Path) -> None:
    """Angle between two models' rays after the best aligning rotation, in microradians."""
    w, h = image_size
    nx, ny = int(np.ceil(w / step)), int(np.ceil(h / step))
    img = np.full((ny, nx), np.nan)
    ix = np.clip((pixels[:, 0] / step).astype(int), 0, nx - 1)
    iy = np.clip((pixels[:, 1] / step).astype(int), 0, ny - 1)
    img[iy, ix] = angle_rad * 1e6
    fig, ax = subplots(1, (7.5, 5))
    im = ax.imshow(img, extent=(0, w, h, 0), cmap="magma", norm=_log_norm(img[np.isfinite(img)]),
                   interpolation="nearest")
    colour_bar(fig, im, ax, "ray angle difference (urad, log scale)")
    ax.set(aspect="equal", xlabel="u (px)", ylabel="v (px)")
    ax.set_title(title, fontsize=9)
    _save(fig, path)


@one_at_a_time
def diff_sigma_png(pixels: np.ndarray, ratio: np.ndarray, image_size: tuple[int, int],
                   step: float, level: float, title: str, path: Path) -> None:
    """Difference divided by the combined sigma, with the `level` contour drawn white."""
    w, h = image_size
    nx, ny = int(np.ceil(w / step)), int(np.ceil(h / step))
    img = np.full((ny, nx), np.nan)
    ix = np.clip((pixels[:, 0] / step).astype(int), 0, nx - 1)
    iy = np.clip((pixels[:, 1] / step).astype(int), 0, ny - 1)
    img[iy, ix] = ratio
    finite = img[np.isfinite(img)]
    top = max(2 * level, float(np.percentile(finite, 99)) if finite.size else 2 * level)
    fig, ax = subplots(1, (7.5, 5))
    im = ax.imshow(img, extent=(0, w, h, 0), cmap="RdYlBu_r", vmin=0, vmax=top,
                   interpolation="nearest")
    colour_bar(fig, im, ax, "difference / combined 1-sigma")
    if finite.size and np.nanmax(img) > level > np.nanmin(img):
        ax.contour(np.nan_to_num(img, nan=0.0), levels=[level], colors="white", linewidths=1.2,
                   extent=(0, w, 0, h), origin="upper")
    ax.set(aspect="equal", xlabel="u (px)", ylabel="v (px)", xlim=(0, w), ylim=(h, 0))
    ax.set_title(title, fontsize=9)
    _save(fig, path)


@one_at_a_time
def guidance_png(before: np.ndarray, after: np.ndarray, outline: np.ndarray,
                 image_size: tuple[int, int], title: str, path: Path) -> None:
    """Predicted ray-sigma maps now and after the suggested pose, with its screen outline."""
    w, h = image_size
    fig, axes = subplots(2, (12, 4.6))
    both = np.concatenate([before[np.isfinite(before)], after[np.isfinite(after)]]) * 1e6
    norm = _log_norm(both)
    for ax, img, name in ((axes[0], before, "now"), (axes[1], after, "after the suggested pose")):
        im = ax.imshow(img * 1e6, extent=(0, w, h, 0), cmap="inferno", norm=norm,
                       interpolation="bilinear")
        ax.set(aspect="equal", xlim=(0, w), ylim=(h, 0))
        ax.set_title(f"predicted ray 1-sigma {name}\nworst {np.nanmax(img) * 1e6:.3g} urad "
                     "(blank: beyond 70 deg)", fontsize=9)
        colour_bar(fig, im, ax, "urad (log scale)")
    closed = np.vstack([outline, outline[:1]])
    axes[1].plot(closed[:, 0], closed[:, 1], "c-", lw=2, label="suggested screen")
    axes[1].legend(loc="lower right", fontsize=8)
    fig.suptitle(title)
    _save(fig, path)


@one_at_a_time
def count_png(counts: np.ndarray, title: str) -> bytes:
    """PNG bytes of a per-pixel count image (poses seeing each pixel) with an integer key."""
    import io

    fig, ax = subplots(1, (6.4, 6.4 * counts.shape[0] / counts.shape[1] * 0.85 + 0.6))
    top = max(int(counts.max()), 1)
    im = ax.imshow(counts, cmap="viridis", vmin=-0.5, vmax=top + 0.5, interpolation="nearest")
    fig.colorbar(im, ax=ax, label="poses seeing the pixel", ticks=range(0, top + 1))
    ax.set(title=title, xlabel="u (camera px)", ylabel="v (camera px)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI)
    return buf.getvalue()
