"""Validity rules: why a pixel is not trusted, as one reason code per pixel (0 = valid).

Rules are applied in order; the first that fails names the pixel's reason, so the counts
in the maps' meta say what limited a pose (docs/decoder.md lists them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

REASONS = (
    "valid",
    "no_screen",  # bright flat not brighter than the dark flat: the pixel sees no screen
    "clipped",  # too few unclipped samples in the coarsest period
    "low_modulation",  # coarsest period too noisy to anchor the unwrapping
    "ambiguous",  # competing peaks of the comb product hold too much posterior mass
    "inconsistent",  # the periods disagree beyond the chi-square threshold
    "off_screen",  # decoded position outside the screen extent
    "screen_edge",  # blur kernel or pixel footprint reaches past the screen edge
    "uncertain",  # final sigma above the threshold
)


@dataclass
class AxisChecks:
    """Per-axis quantities the rules look at (1-D arrays over a chunk of pixels)."""

    anchor_ok: Any  # coarsest period has enough kept samples
    anchor_snr: Any  # coarsest period B* / sigma_B
    ambiguity: Any
    chi2: Any
    chi2_limit: Any
    position: Any
    sigma: Any
    blur: Any  # effective blur width (screen px), NaN where not fitted
    extent_px: int


def classify(
    xp: ModuleType,
    contrast_snr: Any,
    axes: list[AxisChecks],
    *,
    min_contrast_snr: float,
    min_modulation_snr: float,
    max_ambiguity: float,
    screen_margin_sigma: float,
    edge_margin_blur: float,
    max_sigma_px: float,
) -> Any:
    """Reason code per pixel (uint8, index into REASONS); 0 where every rule passes."""
    failures: list[Any] = [~(contrast_snr >= min_contrast_snr)]
    per_rule: list[list[Any]] = [[] for _ in range(len(REASONS) - 2)]
    for ax in axes:
        margin = screen_margin_sigma * ax.sigma
        inside = (ax.position >= -0.5 - margin) & (ax.position <= ax.extent_px - 0.5 + margin)
        per_rule[0].append(~ax.anchor_ok)
        per_rule[1].append(~(ax.anchor_snr >= min_modulation_snr))
        per_rule[2].append(~(ax.ambiguity <= max_ambiguity))
        per_rule[3].append(~(ax.chi2 <= ax.chi2_limit))
        per_rule[4].append(~inside)
        reach = edge_margin_blur * xp.where(xp.isfinite(ax.blur), ax.blur, 0.0)
        clear = (ax.position + 0.5 >= reach) & (ax.extent_px - 0.5 - ax.position >= reach)
        per_rule[5].append(~clear)
        per_rule[6].append(~(ax.sigma <= max_sigma_px))
    for rule in per_rule:
        failed = rule[0]
        for other in rule[1:]:
            failed = failed | other
        failures.append(failed)
    reason = xp.zeros(contrast_snr.shape, dtype=xp.uint8)
    for code in range(len(failures), 0, -1):
        reason = xp.where(failures[code - 1], np.uint8(code), reason)
    return reason


# Rows per band of `mark_screen_edges`: its temporaries (a few bytes per pixel of a band)
# stay in cache and are reused, not allocated (and page-faulted) for the whole image.
EDGE_BAND_ROWS = 64


def mark_screen_edges(reason: np.ndarray, rows: tuple[int, int] | None = None) -> np.ndarray:
    """Pixels next to one that sees no screen straddle the screen's edge: mark them (in place)
    and return their flat indices (they were valid).

    `reason` is the (H, W) host array of codes; the footprint of such a pixel covers both
    the screen and its dark surround, so its decoded point is biased. A valid pixel is
    marked where its 3x3 neighbourhood (cut at the image border) holds a `no_screen`
    pixel: that set dilated by one pixel, row-wise then column-wise, band by band. `rows`
    (r0, r1): only those rows are marked (the rows either side must hold their codes).
    """
    dark, h = REASONS.index("no_screen"), reason.shape[0]
    first, stop = rows if rows is not None else (0, h)
    marked = []
    for r0 in range(first, stop, EDGE_BAND_ROWS):
        r1 = min(r0 + EDGE_BAND_ROWS, stop)
        lo, hi = max(r0 - 1, 0), min(r1 + 1, h)  # the band and the rows either side
        near = reason[lo:hi] == dark
        if not near.any():
            continue
        wide = near.copy()
        wide[:, 1:] |= near[:, :-1]
        wide[:, :-1] |= near[:, 1:]
        rows_here = np.arange(r0, r1)
        touched = (wide[rows_here - lo] | wide[np.maximum(rows_here - 1, 0) - lo]
                   | wide[np.minimum(rows_here + 1, h - 1) - lo])
        marked.append(np.flatnonzero(touched & (reason[r0:r1] == 0)) + r0 * reason.shape[1])
    edge = np.concatenate(marked) if marked else np.zeros(0, dtype=np.int64)
    reason.reshape(-1)[edge] = REASONS.index("screen_edge")
    return edge


# the maps hidden (NaN) where a pixel is not valid; modulation stays (a diagnostic)
HIDDEN = ("x", "y", "sigma_x", "sigma_y", "blur_x", "blur_y")


def hide_invalid(out: dict[str, np.ndarray], mask: np.ndarray, reason: np.ndarray,
                 sl: slice) -> np.ndarray:
    """For the flat pixel range `sl`, just decoded (its outputs still in cache): its `mask`
    (reason 0), NaN in the `HIDDEN` maps of `out` where not valid; returns the range's tally
    of reason codes."""
    codes = reason[sl]
    hidden = ~np.equal(codes, 0, out=mask[sl])
    for key in HIDDEN:
        np.copyto(out[key][sl], np.nan, where=hidden)
    # (one count per code: a fifth of bincount's time on uint8 codes, which it widens first)
    return np.array([np.count_nonzero(codes == code) for code in range(len(REASONS))])


class FinalRows:
    """The rows of a decode's outputs that are final while later pixel ranges still decode.

    A row's screen-edge pass (`mark_screen_edges`) reads the rows either side, so rows
    become final one row behind the decoded pixels: after each `decoded` call the edges of
    the rows it completed are marked, their pixels hidden too, and `on_final(rows)` hears
    how many leading rows will not change again (a resident maps buffer writes them to disk
    while the rest decodes)."""

    def __init__(self, reason: np.ndarray, mask: np.ndarray, out: dict[str, np.ndarray],
                 on_final: Callable[[int], None] | None = None) -> None:
        self.reason, self.mask, self.out, self.on_final = reason, mask, out, on_final
        self.rows = 0  # rows final so far
        self.edges = 0  # screen-edge pixels marked so far

    def decoded(self, pixels: int) -> None:
        """The first `pixels` pixels (row-major, after `hide_invalid`) hold their codes: the
        rows that completes are final once whole bands (or the image) are decoded."""
        h, w = self.reason.shape
        rows = h if pixels >= h * w else max(pixels // w - 1, 0)  # (the next row is read)
        if rows < h and rows - self.rows < EDGE_BAND_ROWS:
            return
        edge = mark_screen_edges(self.reason, (self.rows, rows))
        self.mask[edge] = False
        for key in HIDDEN:
            self.out[key][edge] = np.nan
        self.edges += edge.size
        self.rows = rows
        if self.on_final is not None:
            self.on_final(rows)

    def counts(self, tallies: list[np.ndarray]) -> dict[str, int]:
        """The image's pixel counts by reason, from the ranges' `hide_invalid` tallies and
        the edges marked (every row final)."""
        tally = np.sum(tallies, axis=0)
        tally[0] -= self.edges
        tally[REASONS.index("screen_edge")] += self.edges
        return {name: int(tally[code]) for code, name in enumerate(REASONS)}
