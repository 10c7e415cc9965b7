"""The calibration report: one HTML page that opens with its verdict, and the PNGs behind it.

The page links images by relative name only; `self_contained` turns it into one file with
the images inlined, for mailing or archiving with the model.
"""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path
from typing import Any

import numpy as np

from calibration import report_plots
from calibration.report_data import Download, ReportData, ReportHeader, coverage_counts
from calibration.report_verdict import GLOSSARY, PARAM_SIGMA_FRACTION, Verdict
from calibration.uncertainty import MAX_FIELD_ANGLE_DEG, worst_ray_sigma

REPORT_PAGE = "report.html"
# Named in each page's head: a stored report of an older layout is drawn again when served.
REPORT_FORMAT = "phasecal.report/2"
# Where the links to related pages go: a served report lists the calibrations of its
# session as they are when it is opened, not as they were when it was drawn.
COMPARE_MARKER = "<!-- compare -->"
STYLE = """body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1100px;color:#222;
padding:0 1em}table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #ccc;
padding:3px 8px;text-align:right;vertical-align:top}th{background:#f3f3f3}
td:first-child,th:first-child{text-align:left}
table.checks td,table.checks th,table.header td{text-align:left}
img{max-width:100%;height:auto;border:1px solid #ddd;margin:.3em 0}
.fail{color:#b00;font-weight:bold}.warn{color:#a60;font-weight:bold}.pass{color:#070;
font-weight:bold}.badge{display:inline-block;font-size:1.3em;padding:.2em .6em;
border-radius:4px;border:2px solid}
.explain{font-size:.9em;color:#444;margin:.2em 0 1em}figcaption{font-size:.9em;color:#555;
margin-bottom:1.2em}dt{font-weight:bold}dd{margin:0 0 .5em 1.5em}
.scroll{overflow-x:auto}
@media (max-width:900px){body{margin:.5em}td,th{padding:2px 4px;font-size:.9em}}
@media print{@page{size:A4;margin:12mm}body{max-width:none;margin:0;padding:0;font-size:10pt}
figure,table,img,.verdict{break-inside:avoid;page-break-inside:avoid}
img{max-width:100%;max-height:250mm}h2{break-after:avoid;page-break-after:avoid}
a{color:inherit;text-decoration:none}.scroll{overflow:visible}}"""


def fmt(value: Any, spec: str = ".4g") -> str:
    """A table cell: numbers to `spec`, None and non-finite as '-', text escaped."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float, np.floating)):
        return format(float(value), spec) if np.isfinite(value) else "-"
    return html.escape(str(value))


def table(header: list[str], rows: list[list[Any]], css: str = "") -> str:
    """An HTML table, numbers formatted by `fmt`, in a box that scrolls on narrow screens."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{fmt(c)}</td>" for c in row) + "</tr>" for row in rows)
    cls = f' class="{css}"' if css else ""
    return f'<div class="scroll"><table{cls}><tr>{head}</tr>{body}</table></div>'


def figure(name: str, caption: str) -> str:
    """An image with its caption (linked by relative name)."""
    return (f'<figure><img src="{name}" alt="{html.escape(caption)}" data-figure="{name}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def explain(term: str) -> str:
    """The plain-words sentence for a term, as a note under the view that uses it."""
    return f'<p class="explain"><b>{html.escape(term)}</b>: {html.escape(GLOSSARY[term])}</p>'


def _header(head: ReportHeader, data: ReportData) -> str:
    w, h = data.model.image_size
    rows = [["session", head.session], ["rig", head.rig], ["cameras", head.cameras],
            ["calibrated", head.date], ["software", head.software],
            ["model", f"{data.model.type_name}, {w} x {h} px"],
            ["poses used", f"{len(head.poses_used)}: {', '.join(head.poses_used)}"],
            ["held-out poses", f"{len(head.heldout)}: {', '.join(head.heldout)}"
             if head.heldout else "none"]]
    body = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>"
                   for k, v in rows)
    return f'<div class="scroll"><table class="header">{body}</table></div>'


def _verdict(verdict: Verdict) -> str:
    status = verdict.status
    words = {"pass": "PASS: the model can be used",
             "warn": "WARN: usable, but read the lines marked warn",
             "fail": "FAIL: do not use this model; see what to do below"}[status]
    rows = "".join(
        f'<tr><td>{html.escape(c.name)}</td><td class="{c.status}">{c.status.upper()}</td>'
        f"<td>{html.escape(c.measured)}</td><td>{html.escape(c.threshold)}</td>"
        f"<td>{html.escape(c.advice)}</td></tr>" for c in verdict.checks)
    suggestion = (f"<p><b>Next pose</b>: {html.escape(verdict.suggestion)}</p>"
                  if verdict.suggestion else "")
    return (f'<div class="verdict"><p><span class="badge {status}" id="verdict" '
            f'data-status="{status}">{words}</span></p>'
            '<div class="scroll"><table class="checks"><tr><th>check</th><th>result</th>'
            "<th>measured</th><th>threshold</th><th>what to do</th></tr>"
            f"{rows}</table></div>{suggestion}</div>")


def downloads_html(downloads: list[Download]) -> str:
    """The downloads as a list of links; one not available says why."""
    items = []
    for d in downloads:
        note = f" ({html.escape(d.note)})" if d.note else ""
        if d.href is None:
            items.append(f"<li>{html.escape(d.label)}: not available{note}</li>")
        else:
            items.append(f'<li><a class="download" href="{html.escape(d.href)}" download>'
                         f"{html.escape(d.label)}</a>{note}</li>")
    return f"<ul>{''.join(items)}</ul>"


def _numbers(data: ReportData) -> str:
    st = data.stats
    sig = data.ray_sigma[np.isfinite(data.ray_sigma)]
    rows = [["RMS residual (camera px)", st.get("rms_px")],
            ["expected RMS from decoded noise (px)", st.get("expected_rms_px")],
            ["noise-floor ratio", st.get("noise_floor_ratio")],
            ["RMS in the screen plane (screen px)", st.get("rms_screen_px")],
            ["noise-floor ratio in the screen plane", st.get("noise_floor_ratio_screen")],
            ["ray 1-sigma median (urad)", float(np.median(sig)) * 1e6 if sig.size else None],
            [f"worst ray 1-sigma within {MAX_FIELD_ANGLE_DEG:g} deg of the axis (urad)",
             worst_ray_sigma(data.model, data.grid, data.ray_sigma) * 1e6],
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
        for k, s in (st.get("param_std") or {}).items():
            if k in named:
                loose = bool(s) and s > PARAM_SIGMA_FRACTION * abs(named[k])
                params.append([k, named[k], s, "undetermined" if loose else ""])
    warnings = "".join(f"<li>{html.escape(w)}</li>" for w in st.get("warnings", []))
    return (table(["quantity", "value"], rows, "numbers") + explain("noise-floor ratio")
            + explain("ray 1-sigma")
            + "<h3>Per pose (recomputed from the stored maps)</h3>"
            + table(["pose", "RMS px", "expected px", "ratio", "points", "outliers"], poses,
                    "poses")
            + (explain("held-out pose") if any(v.heldout for v in data.poses) else "")
            + ("<h3>Parameters</h3>" + table(["parameter", "value", "1-sigma", "flag"], params,
                                             "params")
               + f'<p class="explain">A parameter is flagged undetermined when its 1-sigma '
                 f"exceeds {PARAM_SIGMA_FRACTION:.0%} of its value.</p>"
               if params else "")
            + (f"<h3>Warnings of the fit</h3><ul>{warnings}</ul>" if warnings else "")
            + (f'<h3>How the fit was made</h3><p class="fit-note">'
               f'{html.escape(st["fit_note"])}</p>' if st.get("fit_note") else ""))


def write_report(data: ReportData, out_dir: str | Path, header: ReportHeader,
                 verdict: Verdict, downloads: list[Download] | None = None,
                 links: list[tuple[str, str]] | None = None) -> list[str]:
    """Write every PNG and report.html into `out_dir`; returns the file names written.

    `downloads`: the model and its exports (linked near the top); `links`: (text, URL) of
    related pages (differences to other calibrations of the session); None keeps the
    COMPARE_MARKER for `with_links` to fill when the page is served.
    """
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
    counts, cell_kind = coverage_counts(data)
    plots = (("histogram.png", report_plots.histogram_png, (data.poses,),
              "residual distribution against the expected noise of each point"),
             ("radial.png", report_plots.radial_png, (data,),
              "radial profile: RMS residual and the RMS of each point's expected noise"),
             ("uncertainty.png", report_plots.uncertainty_png, (data,),
              "per-pixel ray direction uncertainty (1-sigma) from the fit's covariance"),
             ("coverage.png", report_plots.coverage_png, (data, counts, cell_kind),
              "coverage: observations per cell (red: empty) and training poses per pixel"))
    for name, fn, args, _ in plots:
        fn(*args, out / name)  # type: ignore[operator]
    head = [(n, c) for n, _, _, c in plots]
    terms = "".join(f"<dt>{html.escape(k)}</dt><dd>{html.escape(v)}</dd>"
                    for k, v in GLOSSARY.items())
    body = (f"<h1>{html.escape(header.title)}</h1>" + _header(header, data)
            + "<h2>Verdict</h2>" + _verdict(verdict)
            + ("<h2>Downloads</h2>" + downloads_html(downloads) if downloads else "")
            + "<h2>Numbers</h2><p>Every number and image below is recomputed from the "
              "stored model, fitted poses and decoded maps.</p>" + _numbers(data)
            + "<h2>Residuals</h2>" + figure(*head[0]) + explain("whitened residual")
            + figure(*head[1])
            + "<h2>Uncertainty and coverage</h2>" + figure(*head[2]) + figure(*head[3])
            + explain("coverage cell")
            + "<h2>Per pose</h2>" + "".join(figure(n, c) for n, c in figs)
            + COMPARE_MARKER
            + f"<h2>Terms</h2><dl>{terms}</dl>")
    page = (f"<!doctype html><html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<meta name='generator' content='{REPORT_FORMAT}'>"
            f"<title>{html.escape(header.title)}</title><style>{STYLE}</style></head>"
            f"<body>{body}</body></html>")
    (out / REPORT_PAGE).write_text(page if links is None else with_links(page, links),
                                   encoding="utf-8")
    return [*(n for n, _ in head), *(n for n, _ in figs), REPORT_PAGE]


def is_current(page_head: str) -> bool:
    """Whether a stored page (its first kilobytes suffice) has this layout."""
    return f"content='{REPORT_FORMAT}'" in page_head


def with_links(page: str, links: list[tuple[str, str]]) -> str:
    """The page with its "Compare" section: (text, URL) of related pages (none: no section)."""
    items = "".join(f'<li><a href="{html.escape(u)}">{html.escape(t)}</a></li>'
                    for t, u in links)
    return page.replace(COMPARE_MARKER, f"<h2>Compare</h2><ul>{items}</ul>" if items else "")


_IMG_SRC = re.compile(r'src="([A-Za-z0-9_.-]+\.png)"')
_LINK = re.compile(r'<a ([^>]*?)href="([^"#][^"]*)"([^>]*)>(.*?)</a>', re.S)


def self_contained(page: str, folder: Path) -> str:
    """The page as one file: its PNGs inlined as data URIs, and every link to another file
    or route written out as text (the address to ask the service for), so nothing in it
    refers outside the file."""
    def inline(m: re.Match[str]) -> str:
        data = base64.b64encode((folder / m.group(1)).read_bytes()).decode("ascii")
        return f'src="data:image/png;base64,{data}"'

    def as_text(m: re.Match[str]) -> str:
        return f"{m.group(4)} (<code>{m.group(2)}</code>)"

    return _LINK.sub(as_text, _IMG_SRC.sub(inline, page))
