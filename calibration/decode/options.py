"""Decoder settings (`DecodeOptions`): validity thresholds and unwrapping limits."""

from __future__ import annotations

from dataclasses import dataclass, fields


@dataclass(frozen=True)
class DecodeOptions:
    """Thresholds that decide which pixels are trusted; see docs/decoder.md for the reasoning.

    - `max_sigma_px`: pixels whose final 1-sigma exceeds this (screen px) are invalid.
    - `min_contrast_snr`: bright-minus-dark flat contrast over its noise; below: sees no screen.
    - `min_modulation_snr`: coarsest-period modulation B* over its noise sigma_B; below: the
      unambiguous phase is too noisy to anchor the unwrapping.
    - `max_ambiguity`: posterior mass allowed on competing (separated) peaks of the comb product.
    - `consistency_p`: a pixel whose periods disagree (chi-square of the fused positions)
      beyond this tail probability is invalid.
    - `screen_margin_sigma`: decoded positions further than this many sigma outside the
      screen are invalid (off-screen).
    - `edge_margin_blur`: decoded points closer to the screen edge than this many blur
      widths are invalid (the blur kernel reaches past the edge and biases them).
    - `saturation_margin`: samples at or above `saturation_dn * (1 - margin)` count as
      clipped (a saturated pixel's read noise spreads its values just below the maximum).
    - `chunk_pixels`: pixels processed at once when finishing (bounds temporary memory).
    """

    max_sigma_px: float = 1.0
    min_contrast_snr: float = 5.0
    min_modulation_snr: float = 8.0
    max_ambiguity: float = 1e-6
    consistency_p: float = 1e-6
    screen_margin_sigma: float = 3.0
    edge_margin_blur: float = 3.0
    saturation_margin: float = 0.02
    chunk_pixels: int = 1 << 16

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (value > 0 or (f.name == "saturation_margin" and value == 0)):
                raise ValueError(f"DecodeOptions.{f.name}: must be > 0, got {value!r}")
        for name in ("max_ambiguity", "consistency_p", "saturation_margin"):
            if getattr(self, name) >= 1:
                raise ValueError(f"DecodeOptions.{name}: must be < 1, got {getattr(self, name)!r}")
