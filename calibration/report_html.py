"""The calibration report: one self-describing HTML page and the PNGs behind it, and the
model-versus-model difference map. Pages link images by relative name only."""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

import numpy as np

from calibration import report_plots
from calibration.compare import ray_angle_difference
from calibration.models.base import CameraModel
from calibration.report_data import ReportData

REPORT_PAGE = "report.html"
_STYLE = """body{font-family:system-ui,sans-serif;margin:1.5em;max-width:1100px;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #ccc;padding:3px 8px;
text-align:right}th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}
img{max-width:100%;border:1px solid #ddd;margin:.3em 0}.bad{color:#b00;font-weight:bold}
.ok{color:#070;font-weight:bold}figcaption{font-size:.9em;color:#555;margin-bottom:1.2em}"""


def _fmt(value: Any, spec: str = ".4g") -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float, np.floating)):
        return format(float(value), spec) if np.isfinite(value) else "-"
    return html.escape(str(value))


def _table(header: list[str], rows: list[list[Any]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _figure(name: str, caption: str) -> str:
    return (f'<figure><img src="{name}" alt="{html.escape(caption)}" data-figure="{name}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def _numbers(data: ReportData) -> str:
    st = data.stats
    ok = st.get("model_adequate")
    verdict = ('<span class="ok">model adequate</span>' if ok else
               '<span class="bad">model inadequate: residuals above the noise floor</span>')
    sig = data.ray_sigma[np.isfinite(data.ray_sigma)]
    rows = [["RMS residual (camera px)", st.get("rms_px")],
            ["expected RMS from decoded noise (px)", st.get("expected_rms_px")],
            ["noise-floor ratio", st.get("noise_floor_ratio")],
            ["RMS in the screen plane (screen px)", st.get("rms_screen_px")],
            ["noise-floor ratio in the screen plane", st.get("noise_floor_ratio_screen")],
            ["ray 1-sigma median (urad)", float(np.median(sig)) * 1e6 if sig.size else None],
            ["ray 1-sigma max (urad)", float(np.max(sig)) * 1e6 if sig.size else None],
            ["iterations", st.get("iterations")], ["fit time (s)", st.get("wall_s")]]
    held = st.get("heldout") or {}
    if held:
        rows += [["held-out RMS (px)", held.get("rms_px")],
                 ["held-out noise-floor ratio", held.get("noise_floor_ratio")]]
    poses = [[v.label + (" (held-out)" if v.heldout else ""), v.stats["rms_px"],
              v.stats["expected_rms_px"], v.stats["noise_floor_ratio"], v.stats["n_points"],
              v.stats["outlier_fraction"]] for v in data.poses]
    params: list[list[Any]] = []
    if hasattr(data.model, "param_names"):  # parametric models: named values and their std
        named = dict(zip(data.model.param_names(), data.model.get_params().tolist(),
                         strict=True))
        params = [[k, named[k], s] for k, s in (st.get("param_std") or {}).items() if k in named]
    warnings = "".join(f"<li>{html.escape(w)}</li>" for w in st.get("warnings", []))
    return (f"<p>{verdict}</p>" + _table(["quantity", "value"], rows)
            + "<h3>Per pose (recomputed from the stored maps)</h3>"
            + _table(["pose", "RMS px", "expected px", "ratio", "points", "outliers"], poses)
            + ("<h3>Parameters</h3>" + _table(["parameter", "value", "1-sigma"], params)
               if params else "")
            + (f"<h3>Warnings</h3><ul>{warnings}</ul>" if warnings else ""))


def write_report(data: ReportData, out_dir: str | Path, title: str,
                 links: list[tuple[str, str]] | None = None) -> list[str]:
    """Write every PNG and report.html into `out_dir`; returns the file names written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    size = data.model.image_size
    figs: list[tuple[str, str]] = []
    for i, view in enumerate(data.poses):
        name = f"{'heldout' if view.heldout else 'pose'}_{i:02d}.png"
        report_plots.pose_png(view, size, out / name)
        kind = "held-out pose, located by PnP with the model" if view.heldout else "training pose"
        figs.append((name, f"{view.label} ({kind}): residual vectors with a reference arrow, "
                           "and the binned RMS magnitude"))
    plots = (("histogram.png", report_plots.histogram_png, data.poses,
              "residual distribution against the expected noise of each point"),
             ("radial.png", report_plots.radial_png, data,
              "radial profile: RMS residual and the RMS of each point's expected noise"),
             ("uncertainty.png", report_plots.uncertainty_png, data,
              "per-pixel ray direction uncertainty (1-sigma) from the fit's covariance"),
             ("coverage.png", report_plots.coverage_png, data,
              "coverage: observations per cell and training poses per pixel"))
    for name, fn, arg, _ in plots:
        fn(arg, out / name)  # type: ignore[operator]
    head = [(n, c) for n, _, _, c in plots]
    link_html = "".join(f'<li><a href="{html.escape(u)}">{html.escape(t)}</a></li>'
                        for t, u in links or [])
    body = (f"<h1>{html.escape(title)}</h1><p>Model <b>{html.escape(data.model.type_name)}</b>, "
            f"{size[0]}x{size[1]} px. Every number and image below is recomputed from the "
            "stored model, fitted poses and decoded maps.</p><h2>Numbers</h2>"
            + _numbers(data) + "<h2>Residuals</h2>"
            + "".join(_figure(n, c) for n, c in head[:2])
            + "<h2>Uncertainty and coverage</h2>" + "".join(_figure(n, c) for n, c in head[2:])
            + "<h2>Per pose</h2>" + "".join(_figure(n, c) for n, c in figs)
            + (f"<h2>Compare</h2><ul>{link_html}</ul>" if link_html else ""))
    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}"
            f"</title><style>{_STYLE}</style></head><body>{body}</body></html>")
    (out / REPORT_PAGE).write_text(page, encoding="utf-8")
    return [*(n for n, _ in head), *(n for n, _ in figs), REPORT_PAGE]


def write_diff(model_a: CameraModel, model_b: CameraModel, out_dir: str | Path,
               pixels: np.ndarray | None = None, step_px: float = 4.0,
               names: tuple[str, str] = ("a", "b")) -> dict[str, Any]:
    """Ray-angle difference of two models after the best rotation: diff.png + diff.json."""
    if model_a.image_size != model_b.image_size:
        raise ValueError(f"diff: image sizes differ ({model_a.image_size} vs "
                         f"{model_b.image_size})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    d = ray_angle_difference(model_a.unproject, model_b.unproject, model_a.image_size,
                             step_px=step_px, pixels=pixels)
    summary = {"a": names[0], "b": names[1], "rms_urad": d["rms_rad"] * 1e6,
               "max_urad": d["max_rad"] * 1e6,
               "p95_urad": float(np.nanpercentile(d["angle_rad"], 95)) * 1e6,
               "rotation_b_from_a": np.asarray(d["rotation"]).tolist(),
               "pixels_compared": int(np.isfinite(d["angle_rad"]).sum()), "image": "diff.png"}
    report_plots.diff_png(d["pixels"], d["angle_rad"], model_a.image_size, step_px,
                          f"{names[0]} vs {names[1]}\nRMS {summary['rms_urad']:.3g} urad, "
                          f"max {summary['max_urad']:.3g} urad after the best rotation",
                          out / "diff.png")
    (out / "diff.json").write_text(json.dumps(summary, indent=1), encoding="utf-8")
    return summary
