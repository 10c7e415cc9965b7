"""The compiled decode keeps its maps: small stacks in every configuration the kernels have a
path for (unclipped, clipped border, partly clipped; noise given or from residuals) decode
to the maps stored in data/reference_maps.npz (made by the decoder before its kernels were
regrouped for faster loading) to float32 rounding, masks identical."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration.decode import decode_stack
from tests.calibration.decode.reference_stacks import (
    CONFIGS,
    reference_noise,
    reference_plan,
    reference_stack,
)

REFERENCE = Path(__file__).parent / "data" / "reference_maps.npz"
FLOAT_PLANES = ("x", "y", "sigma_x", "sigma_y", "modulation_x", "modulation_y", "blur_x",
                "blur_y")
RTOL = 2.0 ** -22  # two float32 ulps


@pytest.fixture(scope="module")
def reference() -> dict[str, np.ndarray]:
    with np.load(REFERENCE) as data:
        return {k: data[k] for k in data.files}


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_compiled_decode_matches_reference_maps(name: str, reference) -> None:
    border, partly, given = CONFIGS[name]
    plan = reference_plan()
    maps = decode_stack(plan, reference_stack(plan, border, partly),
                        noise=reference_noise(partly) if given else None, prepare=True)
    assert np.array_equal(maps.mask, reference[f"{name}/mask"])
    assert maps.mask.sum() > 0.7 * maps.mask.size  # the stacks decode: a comparison of maps
    for plane in FLOAT_PLANES:
        np.testing.assert_allclose(getattr(maps, plane), reference[f"{name}/{plane}"],
                                   rtol=RTOL, atol=0.0, equal_nan=True, err_msg=plane)
