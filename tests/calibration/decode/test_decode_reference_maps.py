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


def test_one_shot_decodes_take_the_kernels_where_they_pay_back(monkeypatch) -> None:
    """A one-off decode (no `prepare`) of a 256x256 stack with the noise from the residuals
    runs the compiled whole-stack finish (numba is loaded for the noise line anyway); with
    the noise given, images below 1 Mpixel keep the NumPy path."""
    import calibration.decode.decoder as decoder_module

    assert decoder_module.one_shot_compiled(256 * 256, None)
    assert not decoder_module.one_shot_compiled(640 * 480, 1.0)
    assert decoder_module.one_shot_compiled(1280 * 1024, 1.0)
    whole = []
    finish_stack = decoder_module.StreamingDecoder.finish_stack

    def recorded(self, *args, **kwargs):
        whole.append(self.compiled_now)
        return finish_stack(self, *args, **kwargs)

    monkeypatch.setattr(decoder_module.StreamingDecoder, "finish_stack", recorded)
    plan = reference_plan()
    stack = reference_stack(plan, False, False, shape=(256, 256))
    maps = decode_stack(plan, stack)
    assert whole == [True] and maps.meta["decoder"]["noise"] == "residual"
    decode_stack(plan, stack, noise=reference_noise(False))
    assert whole == [True]  # the NumPy path: no whole-stack finish
