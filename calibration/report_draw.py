"""Draw a report or a model difference from stored files: the one entry point the CLI and the
service's worker processes call (plain paths in, a folder of files out; picklable inputs).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calibration.formats import load_model_any
from calibration.guidance import SessionFit, suggest_next_pose
from calibration.models.base import CameraModel, load_model
from calibration.report_data import (
    Download,
    ReportData,
    ReportHeader,
    fit_ray_sigma,
    gather,
)
from calibration.report_diff import RaySigmaMap, write_diff
from calibration.report_html import write_report
from calibration.report_verdict import assess, empty_regions, loose_parameters
from calibration.shared.maps import load_maps
from calibration.shared.plan import read_plan
from calibration.uncertainty import RAY_SIGMA_GRID, model_ray_sigma, sensor_grid


@dataclass
class ReportInputs:
    """The stored files of one calibration and what the page says around them."""

    model: str  # model.json
    plan: str  # the session's plan.json (screen geometry)
    maps: list[str]  # training poses' maps.npz, in the fit's order
    heldout_maps: list[str] = field(default_factory=list)
    result: str | None = None  # result.json; without it each pose is located by PnP
    labels: list[str] | None = None
    header: ReportHeader = field(default_factory=lambda: ReportHeader("Calibration report"))
    downloads: list[Download] = field(default_factory=list)
    # (text, URL) of related pages; None: filled in when served (`report_html.with_links`)
    links: list[tuple[str, str]] | None = field(default_factory=list)


def guidance_advice(data: ReportData) -> str:
    """The pose guidance's next pose in words, planned with this calibration's own fit
    (parametric models; '' for others, or when no candidate pose can be placed)."""
    if not hasattr(data.model, "param_names"):
        return ""
    train = [v for v in data.poses if not v.heldout]
    fit = SessionFit(data.model, [(v.rotation, v.translation) for v in train],
                     data.train_points, data.stats.get("param_std"))
    try:
        s = suggest_next_pose(fit, data.screen)
    except (ValueError, np.linalg.LinAlgError):
        return ""
    if not s.helps:
        return s.advice
    return f"place the screen {s.placement.words(data.model.image_size)}; {s.advice}"


def draw_report(inputs: ReportInputs, out_dir: str) -> list[str]:
    """Every PNG and report.html of one calibration into `out_dir`; returns the names."""
    model = load_model(inputs.model)
    result = json.loads(Path(inputs.result).read_text()) if inputs.result else {}
    screen = read_plan(inputs.plan).screen
    data = gather(model, result, [load_maps(m) for m in inputs.maps],
                  [load_maps(m) for m in inputs.heldout_maps], screen, labels=inputs.labels)
    weak = bool(empty_regions(data)[1] or loose_parameters(data))
    verdict = assess(data, guidance_advice(data) if weak else "")
    return write_report(data, out_dir, inputs.header, verdict, inputs.downloads, inputs.links)


@dataclass
class FitFiles:
    """What a fit's ray uncertainty is recomputed from: its result, plan and training maps."""

    result: str
    plan: str
    maps: list[str]


@dataclass
class DiffInputs:
    """Two models, their names, where to compare them, and each fit's files (if known)."""

    model_a: str
    model_b: str
    names: tuple[str, str]
    out_dir: str
    coverage_maps: list[str] = field(default_factory=list)  # compare only pixels these saw
    step_px: float = 4.0
    fits: tuple[FitFiles | None, FitFiles | None] = (None, None)


def ray_sigma_map(model: CameraModel, fit: FitFiles | None) -> RaySigmaMap | None:
    """A fit's ray-sigma map for a comparison after the best rotation, without the part a
    rotation of every ray explains: parametric models from their fit's files (None without
    the files), sGCC from the model's own coefficient covariance."""
    nx, ny = RAY_SIGMA_GRID
    if getattr(model, "covariance", None) is not None:
        sigma, method = model_ray_sigma(model, sensor_grid(model.image_size, nx, ny),
                                        rotation_free=True)
    elif fit is not None:
        result = json.loads(Path(fit.result).read_text())
        _, sigma, method = fit_ray_sigma(model, result, [load_maps(m) for m in fit.maps],
                                         read_plan(fit.plan).screen, rotation_free=True)
    else:
        return None
    if not np.isfinite(sigma).any():
        return None
    return RaySigmaMap((ny, nx), sigma, method)


def draw_diff(inputs: DiffInputs) -> dict[str, Any]:
    """diff.html and its images and numbers for two stored models; returns the summary."""
    a, b = load_model_any(inputs.model_a), load_model_any(inputs.model_b)
    pixels = None
    step = inputs.step_px
    if inputs.coverage_maps:
        stride = max(1, int(step))
        union = np.any([load_maps(m).mask for m in inputs.coverage_maps], axis=0)[::stride,
                                                                                  ::stride]
        v, u = np.nonzero(union)
        pixels = np.stack([u * stride, v * stride], axis=1).astype(np.float64)
        step = float(stride)
    sigmas = (ray_sigma_map(a, inputs.fits[0]), ray_sigma_map(b, inputs.fits[1]))
    return write_diff(a, b, inputs.out_dir, pixels, step, inputs.names, sigmas)


__all__ = ["DiffInputs", "FitFiles", "ReportInputs", "draw_diff", "draw_report",
           "guidance_advice", "ray_sigma_map"]
