"""The report of a rig calibration: every camera (its model's key numbers, its residuals in the
joint fit, how much of its own sensor its views covered) and every camera's extrinsics with
their 1-sigma, under one verdict against stated thresholds, with the rig model's downloads.

A lab reading it decides whether the rig model can be used for stereo or triangulation, or
which camera needs more views; it is drawn from stored files only (rig.json, result.json and
each camera's decoded maps, or for a rig fitted to board observations each camera's
observation files), so it is the same page whenever it is drawn again. Without result.json
(a rig model from elsewhere) it draws what rig.json itself keeps.
"""

from __future__ import annotations

import html
import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from matplotlib.patches import Rectangle
from scipy.spatial.transform import Rotation

from calibration.evaluate import ADEQUATE_RATIO
from calibration.figures import one_at_a_time, subplots
from calibration.formats import FILE_NAMES, ExportOptions
from calibration.models.base import ModelError
from calibration.models.parametric import PinholeFamily
from calibration.report_data import COVERAGE_CELLS, Download, ReportHeader
from calibration.report_downloads import export_offers
from calibration.report_html import REPORT_PAGE, STYLE, downloads_html, figure, fmt, table
from calibration.report_verdict import (
    EMPTY_CELLS_FAIL,
    FAIL,
    NOISE_RATIO_FAIL,
    PASS,
    WARN,
    Check,
    Verdict,
)
from calibration.rig_export import RIG_FILE_NAMES, rig_export_bytes
from calibration.shared.maps import load_maps
from calibration.shared.observations import load_observations
from calibration.shared.rig_model import RigModel, load_rig

RIG_REPORT_FORMAT = "phasecal.rig-report/1"
# Extrinsics: the translation's 1-sigma as a fraction of the camera's baseline (a stereo
# depth error scales with it), and the rotation's 1-sigma (a rotation error of e rad moves a
# point at distance Z by e * Z: 1 mrad is 1 mm at 1 m).
BASELINE_SIGMA_WARN = 0.005
BASELINE_SIGMA_FAIL = 0.02
ROTATION_SIGMA_WARN_MRAD = 1.0
ROTATION_SIGMA_FAIL_MRAD = 5.0
# A board view covers the pixels near its detected points: each point is drawn as a disc of
# this fraction of the sensor's shorter side (a few px), so sparse corners read as a region.
POINT_RADIUS_FRACTION = 1 / 60


@dataclass
class RigReportInputs:
    """The stored files a rig report is drawn from (paths, so it can run on a worker).

    Coverage comes from each camera's decoded maps of a screen session or, for a rig
    fitted to board observations, from its observation files: one or the other."""

    rig: str  # rig.json (phasecal.rig/1)
    # result.json of the joint fit ({"stats": ...}); None: the statistics the rig model
    # carries (its own and each camera's per-view rows; no held-out scores)
    result: str | None
    maps: dict[str, list[str]]  # camera -> its decoded maps of the training views
    header: ReportHeader
    downloads: list[Download] = field(default_factory=list)
    # camera -> its observation files (phasecal.observations/1) of the training views
    observations: dict[str, list[str]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.maps and self.observations:
            raise ValueError("a rig report's coverage comes from maps or from observations, "
                             "not both")


@dataclass(frozen=True)
class CoverageWords:
    """How the page names what its coverage counts (decoded pixels of a screen, or detected
    points of a board) and where a camera's noise comes from."""

    colorbar: str
    title: str
    caption: str
    target: str  # what a new view puts into an empty corner
    noise: str  # the noise whitened residuals are divided by
    sigma: str  # one residual's sigma


DECODED_COVERAGE = CoverageWords(
    "views decoded", "views per pixel",
    "how many training views decoded each pixel; cells outlined red were seen by none",
    "the screen", "its decoded noise", "its decoded sigma")
POINT_COVERAGE = CoverageWords(
    "views with a point here", "views with a detected point nearby",
    "how many training views detected a board point near each pixel (each point drawn as a "
    "small disc); cells outlined red hold no view's point",
    "the board", "the noise of its detected points", "its point's pixel sigma")


@dataclass
class CameraSummary:
    """One camera's lines of the report."""

    name: str
    model_type: str
    image_size: tuple[int, int]
    key_numbers: dict[str, float]
    rms: float | None  # RMS residual in the joint fit (px, or mm on the target for rays)
    rms_unit: str
    whitened_rms: float | None
    views: int
    coverage: np.ndarray  # (ny, nx) views seeing each coverage cell
    poses_per_pixel: np.ndarray  # (H, W)


@dataclass
class ExtrinsicsSummary:
    """One non-reference camera's pose relative to the reference, with its 1-sigma."""

    name: str
    baseline_mm: float
    rotation_deg: float
    translation_mm: np.ndarray  # (3,) camera centre in the reference frame
    sigma_translation_mm: float  # norm of the three 1-sigmas
    sigma_rotation_mrad: float


def _key_numbers(model: Any) -> dict[str, float]:
    if isinstance(model, PinholeFamily):
        return {"fx": model.fx, "fy": model.fy, "cx": model.cx, "cy": model.cy}
    return {}


def _coverage(maps_paths: list[str], size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Views per coverage cell (ny, nx) and views per pixel (H, W) of one camera."""
    w, h = size
    per_pixel = np.zeros((h, w), dtype=np.int32)
    for path in maps_paths:
        valid = np.isfinite(load_maps(path).x)
        if valid.shape == per_pixel.shape:
            per_pixel += valid
    nx, ny = COVERAGE_CELLS
    vv, uu = np.nonzero(per_pixel > 0)
    counts = np.zeros((ny, nx))
    np.add.at(counts, (np.minimum(vv * ny // h, ny - 1), np.minimum(uu * nx // w, nx - 1)), 1)
    return counts, per_pixel


def _point_coverage(observation_paths: list[str], size: tuple[int, int]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Views with a detected point in each coverage cell (ny, nx), and views with a point
    near each pixel (H, W) of one camera, from its board observations."""
    w, h = size
    nx, ny = COVERAGE_CELLS
    per_pixel = np.zeros((h, w), dtype=np.int32)
    counts = np.zeros((ny, nx))
    radius = max(1, round(min(w, h) * POINT_RADIUS_FRACTION))
    for path in observation_paths:
        obs = load_observations(path)
        uv = obs.image_xy[obs.used()]
        uv = uv[(uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)]
        cells = np.zeros((ny, nx), dtype=bool)
        cells[(uv[:, 1] * ny / h).astype(int), (uv[:, 0] * nx / w).astype(int)] = True
        counts += cells
        seen = np.zeros((h, w), dtype=np.uint8)
        for u, v in np.rint(uv).astype(int):
            cv2.circle(seen, (int(u), int(v)), radius, 1, thickness=-1)
        per_pixel += seen
    return counts, per_pixel


def camera_summaries(rig: RigModel, stats: dict[str, Any], maps: dict[str, list[str]],
                     observations: dict[str, list[str]] | None = None) -> list[CameraSummary]:
    """Each camera's numbers, from the rig model, the joint fit's rows and its maps (or its
    board observations)."""
    rows = stats.get("per_view", [])
    out = []
    for name, cam in rig.cameras.items():
        mine = [r for r in rows if r.get("camera") == name]
        unit = "px" if any("rms_px" in r for r in mine) else "mm"
        rms = [r.get("rms_px", r.get("rms_mm")) for r in mine]
        wrms = [r.get("whitened_rms") for r in mine]
        weights = [r.get("n_points", 0) for r in mine]
        coverage, per_pixel = (
            _point_coverage(observations.get(name, []), cam.model.image_size) if observations
            else _coverage(maps.get(name, []), cam.model.image_size))
        out.append(CameraSummary(
            name, cam.model.type_name, tuple(cam.model.image_size), _key_numbers(cam.model),
            _pooled_rms(rms, weights), unit, _pooled_rms(wrms, weights), len(mine),
            coverage, per_pixel))
    return out


def _pooled_rms(values: list[float | None], weights: list[int]) -> float | None:
    """RMS over all points from per-view RMS values and point counts."""
    pairs = [(v, n) for v, n in zip(values, weights, strict=True) if v is not None and n > 0]
    if not pairs:
        return None
    total = sum(n for _, n in pairs)
    return float(np.sqrt(sum(v * v * n for v, n in pairs) / total))


def extrinsics_summaries(rig: RigModel) -> list[ExtrinsicsSummary]:
    """Every non-reference camera's baseline, rotation and their 1-sigma."""
    out = []
    for name, cam in rig.cameras.items():
        if name == rig.reference:
            continue
        centre = -cam.rotation.T @ cam.translation
        # (SciPy: cv2.Rodrigues gives 0 below 1e-5 rad, finer than a dense fit's sigma)
        angle = float(np.degrees(Rotation.from_matrix(cam.rotation).magnitude()))
        sd = np.sqrt(np.clip(np.diag(cam.covariance), 0, None))
        out.append(ExtrinsicsSummary(name, float(np.linalg.norm(centre)), angle, centre,
                                     float(np.linalg.norm(sd[3:])),
                                     float(np.linalg.norm(sd[:3]) * 1e3)))
    return out


def _graded(value: float, warn: float, fail: float) -> str:
    return PASS if value <= warn else WARN if value <= fail else FAIL


def rig_verdict(cameras: list[CameraSummary], extrinsics: list[ExtrinsicsSummary],
                words: CoverageWords = DECODED_COVERAGE) -> Verdict:
    """Pass/warn/fail per camera (residuals, coverage) and per camera's extrinsics."""
    checks = []
    for c in cameras:
        if c.whitened_rms is not None:
            checks.append(Check(
                f"{c.name}: whitened RMS in the joint fit",
                _graded(c.whitened_rms, ADEQUATE_RATIO, NOISE_RATIO_FAIL), f"{c.whitened_rms:.3g}",
                f"pass <= {ADEQUATE_RATIO:g}, warn <= {NOISE_RATIO_FAIL:g}, fail above",
                f"the camera's residuals exceed {words.noise}: try a model with more "
                "distortion terms for this camera, or check that the rig did not move"))
        empty = int(np.sum(c.coverage == 0))
        frac = empty / c.coverage.size
        status = PASS if empty == 0 else WARN if frac <= EMPTY_CELLS_FAIL else FAIL
        checks.append(Check(
            f"{c.name}: coverage of its sensor", status,
            f"{empty} of {c.coverage.size} cells empty ({frac:.0%})",
            f"pass: none empty, warn <= {EMPTY_CELLS_FAIL:.0%}, fail above",
            f"capture poses that put {words.target} into {c.name}'s empty corners and "
            "edges"))
    for e in extrinsics:
        ratio = e.sigma_translation_mm / max(e.baseline_mm, 1e-9)
        checks.append(Check(
            f"{e.name}: baseline 1-sigma", _graded(ratio, BASELINE_SIGMA_WARN,
                                                   BASELINE_SIGMA_FAIL),
            f"{e.sigma_translation_mm:.3g} mm of {e.baseline_mm:.4g} mm ({ratio:.2%})",
            f"pass <= {BASELINE_SIGMA_WARN:.1%} of the baseline, warn <= "
            f"{BASELINE_SIGMA_FAIL:.0%}, fail above",
            f"capture more poses that {e.name} and the reference see together, at "
            "different tilts and distances"))
        checks.append(Check(
            f"{e.name}: rotation 1-sigma",
            _graded(e.sigma_rotation_mrad, ROTATION_SIGMA_WARN_MRAD, ROTATION_SIGMA_FAIL_MRAD),
            f"{e.sigma_rotation_mrad:.3g} mrad",
            f"pass <= {ROTATION_SIGMA_WARN_MRAD:g} mrad, warn <= "
            f"{ROTATION_SIGMA_FAIL_MRAD:g} mrad, fail above",
            f"capture shared poses that fill more of {e.name}'s image"))
    return Verdict(checks, [], [], [])


def rig_downloads(rig: RigModel, cal_id: str, collection: str = "/calibrations"
                  ) -> list[Download]:
    """The rig model and every rig export as links to the service's routes (of the rig's
    own collection: a screen session's calibrations, or the target rig calibrations)."""
    base = f"{collection}/{cal_id}"
    out = [Download("rig model (phasecal.rig/1 JSON)", f"{base}/rig",
                    "every camera's model and extrinsics with covariance"),
           Download("ROS static transforms (every camera)",
                    f"{base}/rig/export?format=ros-transforms", "exact")]
    for a, b in itertools.combinations(rig.cameras, 2):
        pair = f"cameras={a},{b}"
        try:
            rig_export_bytes(rig, "opencv-stereo", cameras=(a, b))
            out.append(Download(f"{a},{b}: OpenCV stereo YAML",
                                f"{base}/rig/export?format=opencv-stereo&{pair}",
                                "cv2.stereoCalibrate's convention, X2 = R X1 + T (mm)"))
        except ModelError as exc:
            out.append(Download(f"{a},{b}: OpenCV stereo YAML", None, str(exc)))
        out.append(Download(f"{a},{b}: stereo rectification maps (NPZ)",
                            f"{base}/rig/export?format=stereo-remap&{pair}",
                            "maps for cv2.remap with R1, R2, P1, P2, Q"))
    for name, cam in rig.cameras.items():
        for offer in export_offers(cam.model):
            query = "".join(f"&{k}={v}" for k, v in offer.options.items())
            href = f"{base}/rig/export?format={offer.fmt}&camera={name}{query}"
            out.append(Download(f"{name}: {offer.label}", href if offer.available else None,
                                offer.note))
    return out


def write_rig_downloads(rig: RigModel, rig_json: Path, out_dir: Path) -> list[Download]:
    """Write the rig model and the rig exports `rig_downloads` offers into `out_dir`, linked
    by file name (a report drawn from files, away from the service)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "rig.json").write_bytes(rig_json.read_bytes())
    out = [Download("rig model (phasecal.rig/1 JSON)", "rig.json",
                    "every camera's model and extrinsics with covariance")]
    # (label, format, file name, rig_export_bytes keywords, note)
    offers: list[tuple[str, str, str, dict[str, Any], str]] = [
        ("ROS static transforms (every camera)", "ros-transforms",
         RIG_FILE_NAMES["ros-transforms"], {}, "exact")]
    for a, b in itertools.combinations(rig.cameras, 2):
        offers += [(f"{a},{b}: OpenCV stereo YAML", "opencv-stereo",
                    f"{a}_{b}_{RIG_FILE_NAMES['opencv-stereo']}", {"cameras": (a, b)},
                    "cv2.stereoCalibrate's convention, X2 = R X1 + T (mm)"),
                   (f"{a},{b}: stereo rectification maps (NPZ)", "stereo-remap",
                    f"{a}_{b}_{RIG_FILE_NAMES['stereo-remap']}", {"cameras": (a, b)},
                    "maps for cv2.remap with R1, R2, P1, P2, Q")]
    for name, cam in rig.cameras.items():
        for offer in export_offers(cam.model):
            if not offer.available:
                out.append(Download(f"{name}: {offer.label}", None, offer.note))
                continue
            opts = ExportOptions(approximate=offer.options.get("approximate") == "true")
            offers.append((f"{name}: {offer.label}", offer.fmt,
                           f"{name}_{FILE_NAMES[offer.fmt]}", {"camera": name, "opts": opts},
                           offer.note))
    for label, export_format, file_name, kwargs, note in offers:
        try:
            data, _ = rig_export_bytes(rig, export_format, **kwargs)
        except ModelError as exc:
            out.append(Download(label, None, str(exc)))
            continue
        (out_dir / file_name).write_bytes(data)
        out.append(Download(label, file_name, note))
    return out


@one_at_a_time
def _draw_coverage(cameras: list[CameraSummary], out_dir: Path, words: CoverageWords
                   ) -> list[str]:
    """One PNG per camera: the number of views that covered each pixel."""
    names = []
    for i, c in enumerate(cameras):
        fig, ax = subplots(1, (6, 4.4))
        im = ax.imshow(c.poses_per_pixel, cmap="viridis", interpolation="nearest",
                       vmin=0, vmax=max(int(c.poses_per_pixel.max(initial=0)), 1))
        fig.colorbar(im, ax=ax, label=words.colorbar)
        w, h = c.image_size
        nx, ny = c.coverage.shape[1], c.coverage.shape[0]
        for iy, ix in zip(*np.nonzero(c.coverage == 0), strict=True):
            ax.add_patch(_cell(ix * w / nx, iy * h / ny, w / nx, h / ny))
        ax.set(title=f"{c.name}: {words.title} (red: empty cells)", xlabel="x (px)",
               ylabel="y (px)")
        fig.tight_layout()
        name = f"coverage_{i:02d}.png"
        fig.savefig(str(out_dir / name), dpi=80)
        names.append(name)
    return names


def _cell(x: float, y: float, w: float, h: float) -> Rectangle:
    """The outline of one empty coverage cell."""
    return Rectangle((x - 0.5, y - 0.5), w, h, fill=False, edgecolor="red", linewidth=1.2)


def _verdict_html(verdict: Verdict) -> str:
    status = verdict.status
    words = {PASS: "PASS: the rig model can be used",
             WARN: "WARN: usable, but read the lines marked warn",
             FAIL: "FAIL: do not use this rig model; see what to do below"}[status]
    rows = "".join(
        f'<tr><td>{html.escape(c.name)}</td><td class="{c.status}">{c.status.upper()}</td>'
        f"<td>{html.escape(c.measured)}</td><td>{html.escape(c.threshold)}</td>"
        f"<td>{html.escape(c.advice)}</td></tr>" for c in verdict.checks)
    return (f'<div class="verdict"><p><span class="badge {status}" id="verdict" '
            f'data-status="{status}">{words}</span></p><div class="scroll"><table '
            'class="checks"><tr><th>check</th><th>result</th><th>measured</th>'
            f"<th>threshold</th><th>what to do</th></tr>{rows}</table></div></div>")


def _header_html(head: ReportHeader, rig: RigModel) -> str:
    rows = [["session", head.session], ["rig", head.rig], ["cameras", head.cameras],
            ["reference camera", rig.reference], ["calibrated", head.date],
            ["software", head.software],
            ["views used", f"{len(head.poses_used)}: {', '.join(head.poses_used)}"],
            ["held-out views", f"{len(head.heldout)}: {', '.join(head.heldout)}"
             if head.heldout else "none"]]
    body = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>"
                   for k, v in rows)
    return f'<div class="scroll"><table class="header">{body}</table></div>'


def _heldout_html(stats: dict[str, Any]) -> str:
    scored = stats.get("heldout") or []
    if not scored:
        return "<p>No view was held out.</p>"
    rows = []
    for view in scored:
        for cam, row in (view.get("cameras") or {}).items():
            rows.append([view.get("view"), cam, row.get("rms_px", row.get("rms_mm")),
                         row.get("whitened_rms")])
    if not rows:
        return f"<pre>{html.escape(json.dumps(scored, indent=1))}</pre>"
    return table(["view", "camera", "RMS miss (px or mm)", "whitened RMS"], rows)


def held_rays_note(stats: dict[str, Any]) -> str:
    """What the extrinsics' sigma of the cameras that kept their own fit's rays includes:
    those rays' uncertainty where the fit carried it (`intrinsics_rays_in_covariance`),
    else nothing of it (a lower bound)."""
    fixed = stats.get("intrinsics_fixed") or []
    carried = [c for c in fixed if c in (stats.get("intrinsics_rays_in_covariance") or [])]
    left_out = [c for c in fixed if c not in carried]
    notes = []
    if carried:
        notes.append(f"{', '.join(carried)} kept the rays of their own fit; their "
                     "extrinsics' sigma includes those rays' uncertainty (that fit's "
                     "covariance).")
    if left_out:
        notes.append(f"{', '.join(left_out)} kept the rays of their own fit; their "
                     "extrinsics' sigma leaves out the rays' uncertainty (a lower bound).")
    return "".join(f"<p class='explain'>{html.escape(n)}</p>" for n in notes)


def rig_report_html(inputs: RigReportInputs, rig: RigModel, stats: dict[str, Any],
                    cameras: list[CameraSummary], extrinsics: list[ExtrinsicsSummary],
                    images: list[str], words: CoverageWords = DECODED_COVERAGE) -> str:
    """The whole page."""
    verdict = rig_verdict(cameras, extrinsics, words)
    keys = sorted({k for c in cameras for k in c.key_numbers}, key=["fx", "fy", "cx", "cy"].index)
    cam_rows = [[c.name, c.model_type, f"{c.image_size[0]} x {c.image_size[1]}",
                 *[c.key_numbers.get(k) for k in keys], c.views,
                 f"{fmt(c.rms)} {c.rms_unit}", c.whitened_rms,
                 f"{np.mean(c.coverage > 0):.0%}"] for c in cameras]
    ext_rows = [[e.name, f"{e.baseline_mm:.4g}", f"{e.rotation_deg:.4g}",
                 ", ".join(f"{v:.4g}" for v in e.translation_mm),
                 f"{e.sigma_translation_mm:.3g}", f"{e.sigma_rotation_mrad:.3g}"]
                for e in extrinsics]
    fixed_note = held_rays_note(stats)
    figures = "".join(figure(n, f"{c.name}: {words.caption}")
                      for n, c in zip(images, cameras, strict=True))
    head = inputs.header
    return (
        f"<!doctype html><html lang='en'><head><meta charset='utf-8'>"
        f"<meta name='viewport' content='width=device-width,initial-scale=1'>"
        f"<meta name='phasecal-report' content='{RIG_REPORT_FORMAT}'>"
        f"<title>{html.escape(head.title)}</title><style>{STYLE}</style></head><body>"
        f"<h1>{html.escape(head.title)}</h1>{_header_html(head, rig)}"
        f"<h2>Verdict</h2>{_verdict_html(verdict)}"
        f"<h2>Downloads</h2>{downloads_html(inputs.downloads)}"
        f"<h2>Cameras</h2>"
        + table(["camera", "model", "image", *keys, "views", "RMS residual", "whitened RMS",
                 "cells covered"], cam_rows).replace("<table", "<table id='cameras'", 1)
        + f"<p class='explain'>Residuals of the joint fit; the whitened RMS divides each "
          f"residual by {words.sigma} (1 means the model explains the data down to the "
          f"noise). Coverage counts a {COVERAGE_CELLS[0]} x {COVERAGE_CELLS[1]} grid of "
          f"each camera's own sensor.</p>"
        + f"<h2>Extrinsics (frame of {html.escape(rig.reference)})</h2>"
        + table(["camera", "baseline (mm)", "rotation (deg)", "centre in reference (mm)",
                 "1-sigma translation (mm)", "1-sigma rotation (mrad)"],
                ext_rows).replace("<table", "<table id='extrinsics'", 1)
        + "<p class='explain'>1-sigma from each camera's 6x6 covariance over (rotation "
          "vector, translation), scaled by the joint fit's reduced chi-square "
          f"({fmt(stats.get('reduced_chi2'))}).</p>{fixed_note}"
        + f"<h2>Held-out views</h2>{_heldout_html(stats)}"
        + f"<h2>Coverage</h2>{figures}</body></html>")


def rig_model_stats(rig: RigModel) -> dict[str, Any]:
    """The joint fit's statistics as far as the rig model keeps them: its own (chi-square,
    extrinsics, cameras held) and each camera's per-view rows."""
    rows = [row for cam in rig.cameras.values()
            for row in (cam.model.stats or {}).get("per_view", [])]
    return {**rig.stats, "per_view": rows}


def draw_rig_report(inputs: RigReportInputs, out_dir: str) -> str:
    """Write report.html and its coverage PNGs into `out_dir`; the page's path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rig = load_rig(inputs.rig)
    stats = (rig_model_stats(rig) if inputs.result is None
             else json.loads(Path(inputs.result).read_text(encoding="utf-8")).get("stats", {}))
    cameras = camera_summaries(rig, stats, inputs.maps, inputs.observations)
    extrinsics = extrinsics_summaries(rig)
    words = POINT_COVERAGE if inputs.observations else DECODED_COVERAGE
    images = _draw_coverage(cameras, out, words)
    page = rig_report_html(inputs, rig, stats, cameras, extrinsics, images, words)
    (out / REPORT_PAGE).write_text(page, encoding="utf-8")
    return str(out / REPORT_PAGE)


__all__ = ["RigReportInputs", "draw_rig_report", "rig_downloads", "rig_model_stats",
           "rig_verdict", "write_rig_downloads"]
