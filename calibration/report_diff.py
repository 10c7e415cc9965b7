"""Two models compared as a page: the angle between their rays after the best aligning
rotation, set against the two fits' combined ray uncertainty.

A difference means something only next to how well each model is known: two fits of the
same camera differ by their noise; a difference many sigmas wide is a real change (a moved
lens, a wrong model).
"""

from __future__ import annotations

import html
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from calibration import report_plots
from calibration.compare import ray_angle_difference
from calibration.models.base import CameraModel
from calibration.report_html import STYLE, table

DIFF_PAGE = "diff.html"
# The models agree when at most this fraction of the compared pixels differ by more than
# 2 combined sigma (for Gaussian errors a few percent do by chance).
AGREE_FRACTION = 0.05
SIGMA_LEVEL = 2.0


@dataclass
class RaySigmaMap:
    """A fit's ray 1-sigma (rad) on a regular sensor grid, and how it was obtained."""

    grid_shape: tuple[int, int]  # (ny, nx) of `calibration.uncertainty.sensor_grid`
    sigma: np.ndarray  # (ny * nx,) rad, NaN where unknown
    method: str

    def at(self, pixels: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
        """Bilinear interpolation at pixels (N, 2)."""
        ny, nx = self.grid_shape
        w, h = image_size
        axes = (np.linspace(0, h - 1, ny), np.linspace(0, w - 1, nx))
        interp = RegularGridInterpolator(axes, self.sigma.reshape(ny, nx), bounds_error=False,
                                         fill_value=np.nan)
        return interp(np.clip(pixels[:, ::-1], 0, [h - 1, w - 1]))


def combined_sigma(pixels: np.ndarray, image_size: tuple[int, int],
                   sigmas: tuple[RaySigmaMap | None, RaySigmaMap | None]) -> np.ndarray | None:
    """sqrt(sigma_a^2 + sigma_b^2) at pixels; None unless both fits have a sigma map."""
    if sigmas[0] is None or sigmas[1] is None:
        return None
    a, b = (s.at(pixels, image_size) for s in sigmas)
    return np.sqrt(a**2 + b**2)


def summarize_difference(angle: np.ndarray, sigma: np.ndarray | None) -> dict[str, Any]:
    """Median, p95, max, RMS (urad); with sigma: the fraction beyond SIGMA_LEVEL combined sigma
    and the verdict."""
    ok = np.isfinite(angle)
    a = angle[ok]
    out: dict[str, Any] = {
        "median_urad": float(np.median(a)) * 1e6, "p95_urad": float(np.percentile(a, 95)) * 1e6,
        "max_urad": float(np.max(a)) * 1e6, "rms_urad": float(np.sqrt(np.mean(a**2))) * 1e6,
        "pixels_compared": int(ok.sum()), "fraction_beyond_2_sigma": None,
        "sigma_median_urad": None, "agree": None}
    if sigma is not None:
        both = ok & np.isfinite(sigma) & (sigma > 0)
        if both.any():
            z = angle[both] / sigma[both]
            frac = float(np.mean(z > SIGMA_LEVEL))
            out.update(fraction_beyond_2_sigma=frac,
                       sigma_median_urad=float(np.median(sigma[both])) * 1e6,
                       agree=frac <= AGREE_FRACTION, pixels_with_sigma=int(both.sum()))
    return out


def verdict_text(summary: dict[str, Any]) -> str:
    """The one-line verdict of a comparison."""
    if summary["agree"] is None:
        return ("cannot be judged: the uncertainty of at least one model is not available, "
                "so the difference cannot be set against it")
    frac = summary["fraction_beyond_2_sigma"]
    if summary["agree"]:
        return (f"the models agree within their uncertainty: {frac:.1%} of the compared "
                f"pixels differ by more than {SIGMA_LEVEL:g} combined sigma "
                f"(threshold {AGREE_FRACTION:.0%})")
    return (f"the models do not agree within their uncertainty: {frac:.1%} of the compared "
            f"pixels differ by more than {SIGMA_LEVEL:g} combined sigma (threshold "
            f"{AGREE_FRACTION:.0%}); the camera or the fit changed beyond the noise")


def _page(summary: dict[str, Any], methods: tuple[str, str]) -> str:
    agree = summary["agree"]
    cls = "warn" if agree is None else "pass" if agree else "fail"
    frac = summary["fraction_beyond_2_sigma"]
    rows = [["median difference (urad)", summary["median_urad"]],
            ["95th percentile (urad)", summary["p95_urad"]],
            ["max difference (urad)", summary["max_urad"]],
            ["RMS difference (urad)", summary["rms_urad"]],
            ["median combined 1-sigma (urad)", summary["sigma_median_urad"]],
            [f"fraction beyond {SIGMA_LEVEL:g} combined sigma",
             None if frac is None else f"{frac:.2%}"],
            ["pixels compared", summary["pixels_compared"]]]
    a, b = html.escape(summary["a"]), html.escape(summary["b"])
    sigma_fig = ('<figure><img src="diff_sigma.png" alt="difference over combined sigma">'
                 "<figcaption>the difference divided by the combined 1-sigma of the two fits; "
                 f"a white line encloses where it exceeds {SIGMA_LEVEL:g} (none: nowhere)"
                 "</figcaption></figure>"
                 if agree is not None else "")
    return (f"<!doctype html><html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<title>Model difference: {a} vs {b}</title><style>{STYLE}</style></head><body>"
            f"<h1>Model difference</h1><p><b>A</b>: {a} ({html.escape(methods[0])})<br>"
            f"<b>B</b>: {b} ({html.escape(methods[1])})</p>"
            f'<p><span class="badge {cls}" id="verdict" data-agree="{agree}">'
            f"{html.escape(verdict_text(summary))}</span></p>"
            + table(["quantity", "value"], rows, "numbers")
            + '<p class="explain">The difference is the angle between the two models\' rays '
              "through the same pixel, after the one rotation that best aligns the two "
              "camera frames (a camera's frame is defined only up to a rotation). The "
              "combined sigma is sqrt(sigma_A^2 + sigma_B^2), each fit's ray 1-sigma from its "
              "own covariance: how far each model may be off from the data it was fitted "
              "to.</p>"
            + '<figure><img src="diff.png" alt="difference map"><figcaption>ray angle '
              "difference after the best rotation (microradians, log colour scale)"
              "</figcaption></figure>" + sigma_fig + "</body></html>")


def write_diff(model_a: CameraModel, model_b: CameraModel, out_dir: str | Path,
               pixels: np.ndarray | None = None, step_px: float = 4.0,
               names: tuple[str, str] = ("a", "b"),
               sigmas: tuple[RaySigmaMap | None, RaySigmaMap | None] = (None, None),
               ) -> dict[str, Any]:
    """diff.html, diff.png, diff_sigma.png (when both uncertainties are known) and diff.json
    comparing two models on `pixels` (default: a grid of `step_px`); returns the summary."""
    if model_a.image_size != model_b.image_size:
        raise ValueError(f"diff: image sizes differ ({model_a.image_size} vs "
                         f"{model_b.image_size})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    size = model_a.image_size
    d = ray_angle_difference(model_a.unproject, model_b.unproject, size, step_px=step_px,
                             pixels=pixels)
    angle = np.asarray(d["angle_rad"])
    sigma = combined_sigma(d["pixels"], size, sigmas)
    methods = tuple(s.method if s is not None else "uncertainty not available"
                    for s in sigmas)
    summary = {"a": names[0], "b": names[1], **summarize_difference(angle, sigma),
               "rotation_b_from_a": np.asarray(d["rotation"]).tolist(),
               "uncertainty": {"a": methods[0], "b": methods[1]},
               "verdict": "", "image": "diff.png", "page": DIFF_PAGE}
    summary["verdict"] = verdict_text(summary)
    report_plots.diff_png(d["pixels"], angle, size, step_px,
                          f"{names[0]} vs {names[1]}\nmedian {summary['median_urad']:.3g}, "
                          f"max {summary['max_urad']:.3g} urad after the best rotation",
                          out / "diff.png")
    if summary["agree"] is not None and sigma is not None:
        summary["sigma_image"] = "diff_sigma.png"
        report_plots.diff_sigma_png(d["pixels"], angle / sigma, size, step_px, SIGMA_LEVEL,
                                    f"difference / combined sigma: "
                                    f"{summary['fraction_beyond_2_sigma']:.1%} beyond "
                                    f"{SIGMA_LEVEL:g}", out / "diff_sigma.png")
    (out / DIFF_PAGE).write_text(_page(summary, methods), encoding="utf-8")  # type: ignore[arg-type]
    (out / "diff.json").write_text(json.dumps(summary, indent=1), encoding="utf-8")
    return summary


__all__ = ["AGREE_FRACTION", "DIFF_PAGE", "RaySigmaMap", "combined_sigma",
           "summarize_difference", "verdict_text", "write_diff"]
