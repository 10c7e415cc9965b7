"""Image sensor: photons to digital numbers with shot/read noise, gain, quantization, clipping."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_BIT_DEPTHS = (8, 10, 12, 16)


@dataclass
class SensorModel:
    """A linear sensor; `dn_per_e` is the 0 dB gain (default: full well maps to the top DN)."""

    bit_depth: int = 12
    full_well_e: float = 10000.0
    read_noise_e: float = 3.0
    dn_per_e: float | None = None
    black_level_dn: float = 0.0
    exact_poisson: bool = True  # False: Gaussian approximation of shot noise (faster)

    def __post_init__(self) -> None:
        """Validate and normalize the fields (errors name the field and what was expected)."""
        if self.bit_depth not in _BIT_DEPTHS:
            raise ValueError(f"bit_depth: expected one of {_BIT_DEPTHS}, got {self.bit_depth}")
        if self.full_well_e <= 0 or self.read_noise_e < 0:
            raise ValueError("full_well_e must be > 0 and read_noise_e >= 0 (electrons)")
        if not 0 <= self.black_level_dn < self.max_dn:
            raise ValueError(
                f"black_level_dn: expected in [0, {self.max_dn}), got {self.black_level_dn}"
            )
        if self.dn_per_e is None:
            self.dn_per_e = (self.max_dn - self.black_level_dn) / self.full_well_e
        if self.dn_per_e <= 0:
            raise ValueError(f"dn_per_e: expected > 0, got {self.dn_per_e}")

    @property
    def max_dn(self) -> int:
        """Largest digital number (saturated pixels read this)."""
        return (1 << self.bit_depth) - 1

    @property
    def dtype(self) -> type[np.unsignedinteger]:
        """Output array dtype: uint8 for 8-bit sensors, uint16 otherwise."""
        return np.uint8 if self.bit_depth == 8 else np.uint16

    def gain(self, gain_db: float = 0.0) -> float:
        """DN per electron at an analog gain in dB."""
        assert self.dn_per_e is not None
        return self.dn_per_e * 10.0 ** (gain_db / 20.0)

    def mean_dn(
        self, irradiance_e_per_s: np.ndarray, exposure_s: float, gain_db: float = 0.0
    ) -> np.ndarray:
        """Noise-free expected DN (before quantization and DN clipping, after full-well clip)."""
        electrons = np.minimum(
            np.asarray(irradiance_e_per_s, np.float64) * exposure_s, self.full_well_e
        )
        return self.black_level_dn + self.gain(gain_db) * electrons

    def expose(
        self,
        irradiance_e_per_s: np.ndarray,
        exposure_s: float,
        gain_db: float,
        rng: np.random.Generator,
    ) -> np.ndarray:
        """One noisy frame: shot noise, full-well clip, read noise, gain, rounding, DN clip."""
        if exposure_s <= 0:
            raise ValueError(f"exposure_s: expected > 0, got {exposure_s}")
        lam = np.maximum(np.asarray(irradiance_e_per_s, np.float64) * exposure_s, 0.0)
        if self.exact_poisson:
            electrons = rng.poisson(lam).astype(np.float64)
        else:
            electrons = lam + np.sqrt(lam) * rng.standard_normal(lam.shape)
        electrons = np.minimum(electrons, self.full_well_e)
        if self.read_noise_e > 0:
            electrons += self.read_noise_e * rng.standard_normal(lam.shape)
        dn = np.floor(self.black_level_dn + self.gain(gain_db) * electrons + 0.5)
        return np.clip(dn, 0, self.max_dn).astype(self.dtype)

    def noise_sigma_dn(self, mean_dn: np.ndarray, gain_db: float = 0.0) -> np.ndarray:
        """Per-pixel noise std (DN) at a mean level: shot + read noise through the gain + rounding.

        Valid below saturation; pixels at the full well or top DN have less noise.
        """
        g = self.gain(gain_db)
        electrons = np.maximum((np.asarray(mean_dn, np.float64) - self.black_level_dn) / g, 0.0)
        return np.sqrt(g * g * (electrons + self.read_noise_e**2) + 1.0 / 12.0)
