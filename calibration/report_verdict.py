"""The report's verdict: pass, warn or fail against stated thresholds, each check naming its
measured value, its threshold and what to do; weak regions of the sensor in words, parameters
the data do not determine, and poses that repeat another.

A lab reads the first screen of a report and decides whether to use the model or capture
more; every line here is written for that decision.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.evaluate import ADEQUATE_RATIO
from calibration.report_data import ReportData, coverage_counts

PASS, WARN, FAIL = "pass", "warn", "fail"
_RANK = {PASS: 0, WARN: 1, FAIL: 2}

# Noise-floor ratio (training and held-out): pass up to the fit's own adequacy limit, fail
# beyond twice that (the residuals are then dominated by what the model cannot describe).
NOISE_RATIO_FAIL = 2 * ADEQUATE_RATIO
# Coverage: any empty cell warns; more than this fraction of the cells empty fails.
EMPTY_CELLS_FAIL = 0.10
# A parameter whose 1-sigma exceeds this fraction of its magnitude is not determined.
PARAM_SIGMA_FRACTION = 0.5
# Two poses closer than both of these repeat each other (no new information).
DUPLICATE_ANGLE_DEG = 2.0
DUPLICATE_SHIFT = 0.02  # of the poses' mean distance

GLOSSARY = {
    "noise-floor ratio": "the RMS residual divided by the RMS the decoder's own noise estimate "
                         "predicts: 1 means the model explains the data down to the noise, "
                         "above 1 means something the model cannot describe is left over.",
    "whitened residual": "a residual divided by the sigma expected from its pixel's decoded "
                         "noise; when the model and the noise estimate are right these follow "
                         "a standard normal distribution (standard deviation 1).",
    "ray 1-sigma": "how far (in microradians) the direction of a pixel's ray may be off, one "
                   "standard deviation, from the fit's covariance: small where many poses "
                   "constrain the model, large where it extrapolates.",
    "held-out pose": "a pose captured but not used in the fit; the model is checked against "
                     "it, which catches a model that fits its own data but not new data.",
    "coverage cell": "one of the rectangles the sensor is divided into to count where the "
                     "training poses saw the screen; an empty cell has no data at all.",
}


@dataclass
class Check:
    """One line of the verdict."""

    name: str
    status: str  # pass, warn or fail
    measured: str
    threshold: str
    advice: str


@dataclass
class Verdict:
    """All checks, the overall status (the worst of them) and the details behind them."""

    checks: list[Check]
    empty_regions: list[tuple[str, int]]  # (part of the sensor, empty cells there)
    loose_parameters: list[tuple[str, float, float]]  # (name, value, 1-sigma)
    duplicates: list[tuple[str, str, float, float]]  # (pose, pose, angle deg, shift mm)
    suggestion: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def status(self) -> str:
        """The worst status of the checks."""
        return max((c.status for c in self.checks), key=_RANK.__getitem__, default=PASS)


def _ratio_check(name: str, ratio: float | None, advice_fail: str) -> Check:
    threshold = (f"pass <= {ADEQUATE_RATIO:g}, warn <= {NOISE_RATIO_FAIL:g}, "
                 f"fail above")
    if ratio is None or not np.isfinite(ratio):
        return Check(name, WARN, "not available", threshold,
                     "the residuals could not be compared with the decoded noise")
    status = PASS if ratio <= ADEQUATE_RATIO else WARN if ratio <= NOISE_RATIO_FAIL else FAIL
    advice = ("nothing to do: the residuals are at the noise level" if status == PASS
              else advice_fail)
    return Check(name, status, f"{ratio:.3g}", threshold, advice)


def sensor_part(u: float, v: float, w: int, h: int) -> str:
    """Plain name of the ninth of the sensor holding pixel (u, v)."""
    col = ("left", "centre", "right")[min(int(3 * u / w), 2)]
    row = ("top", "middle", "bottom")[min(int(3 * v / h), 2)]
    if row == "middle":
        return "centre" if col == "centre" else f"{col} edge"
    return f"{row} edge" if col == "centre" else f"{row}-{col} corner"


def empty_regions(data: ReportData) -> tuple[list[tuple[str, int]], int, int]:
    """Empty coverage cells grouped by part of the sensor (most first), their count and the
    number of cells."""
    counts, _ = coverage_counts(data)
    ny, nx = counts.shape
    w, h = data.model.image_size
    parts: dict[str, int] = {}
    for iy, ix in zip(*np.nonzero(counts == 0), strict=True):
        name = sensor_part((ix + 0.5) * w / nx, (iy + 0.5) * h / ny, w, h)
        parts[name] = parts.get(name, 0) + 1
    ordered = sorted(parts.items(), key=lambda kv: -kv[1])
    return ordered, int(np.sum(counts == 0)), counts.size


def placement_for(part: str) -> str:
    """How to place the screen so that it covers `part` of the image."""
    if part == "centre":
        return "place the screen straight ahead, filling the middle of the image"
    words = part.replace("-", " ").split()[:-1]  # "top-left corner" -> ["top", "left"]
    axis = ("vertical" if set(words) & {"left", "right"} and len(words) == 1
            else "horizontal" if len(words) == 1 else "diagonal")
    return (f"move the screen so that it appears in the {part} of the image, tilted about "
            f"40 degrees about its {axis} axis so that its far edge reaches the border")


def loose_parameters(data: ReportData) -> list[tuple[str, float, float]]:
    """Fitted parameters whose 1-sigma exceeds PARAM_SIGMA_FRACTION of their magnitude."""
    std = data.stats.get("param_std") or {}
    if not std or not hasattr(data.model, "param_names"):
        return []
    values = dict(zip(data.model.param_names(), data.model.get_params().tolist(), strict=True))
    out = []
    for name, sigma in std.items():
        if name in values and sigma and np.isfinite(sigma) and sigma > 0:
            if sigma > PARAM_SIGMA_FRACTION * abs(values[name]):
                out.append((name, float(values[name]), float(sigma)))
    return out


def duplicate_poses(data: ReportData) -> list[tuple[str, str, float, float]]:
    """Pairs of poses (training and held-out) that see the screen from nearly the same place."""
    views = data.poses
    if len(views) < 2:
        return []
    scale = float(np.mean([np.linalg.norm(v.translation) for v in views]))
    out = []
    for i, a in enumerate(views):
        for b in views[i + 1:]:
            rel = a.rotation.T @ b.rotation
            angle = float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0))))
            shift = float(np.linalg.norm(a.translation - b.translation))
            if angle < DUPLICATE_ANGLE_DEG and shift < DUPLICATE_SHIFT * scale:
                out.append((a.label, b.label, angle, shift))
    return out


def assess(data: ReportData, suggestion: str = "") -> Verdict:
    """Every check of the verdict from the report's data; `suggestion` is the pose guidance's
    advice in words (empty: the placement is described from the weak region alone)."""
    st = data.stats
    checks = [_ratio_check(
        "noise-floor ratio (training poses)", st.get("noise_floor_ratio"),
        "the model leaves a systematic error: look at the residual maps for its pattern, try a "
        "model with more terms, and check the screen geometry and the decoding")]
    held = st.get("heldout") or {}
    if held:
        checks.append(_ratio_check(
            "noise-floor ratio (held-out poses)", held.get("noise_floor_ratio"),
            "the model does not predict new poses as well as its own: it may be "
            "over-fitted; use fewer terms or more, better spread poses"))
    else:
        checks.append(Check("held-out error", WARN, "no held-out poses",
                            "at least one held-out pose",
                            "calibrate with one or two poses held out to check the model "
                            "on data it was not fitted to"))
    regions, empty, cells = empty_regions(data)
    where = ", ".join(f"{n} in the {p}" for p, n in regions)
    if empty == 0:
        checks.append(Check("coverage", PASS, f"0 of {cells} cells empty",
                            f"pass: none empty; fail above {EMPTY_CELLS_FAIL:.0%}",
                            "nothing to do: every part of the sensor has data"))
    else:
        status = FAIL if empty > EMPTY_CELLS_FAIL * cells else WARN
        advice = suggestion or "; ".join(placement_for(p) for p, _ in regions[:2])
        checks.append(Check("coverage", status, f"{empty} of {cells} cells empty ({where})",
                            f"pass: none empty; fail above {EMPTY_CELLS_FAIL:.0%}",
                            f"the model there is extrapolated; {advice}"))
    loose = loose_parameters(data)
    n_std = sum(1 for v in (st.get("param_std") or {}).values() if v)  # fixed terms: 0
    if n_std:
        names = ", ".join(f"{k} = {v:.3g} +- {s:.3g}" for k, v, s in loose)
        checks.append(Check(
            "parameter uncertainty", WARN if loose else PASS,
            f"{len(loose)} of {n_std} parameters undetermined" + (f" ({names})" if loose else ""),
            f"1-sigma <= {PARAM_SIGMA_FRACTION:.0%} of the value",
            "the model may be over-parameterised for this data: fit one with fewer terms, "
            "or add poses that tilt the screen and reach the image corners" if loose
            else "nothing to do: every parameter is determined by the data"))
    dups = duplicate_poses(data)
    pairs = ", ".join(f"{a} = {b}" for a, b, _, _ in dups)
    checks.append(Check(
        "duplicate poses", WARN if dups else PASS,
        f"{len(dups)} pair(s)" + (f" ({pairs})" if dups else ""),
        f"no two poses within {DUPLICATE_ANGLE_DEG:g} deg and {DUPLICATE_SHIFT:.0%} of the "
        "distance", "a repeated pose adds no information; replace one of each pair with a "
        "new position or tilt" if dups else "nothing to do"))
    return Verdict(checks, regions, loose, dups, suggestion)


__all__ = ["FAIL", "GLOSSARY", "PASS", "WARN", "Check", "Verdict", "assess", "duplicate_poses",
           "empty_regions", "loose_parameters", "placement_for", "sensor_part"]
