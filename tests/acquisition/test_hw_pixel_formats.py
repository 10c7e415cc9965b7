"""Pixel format unpacking (packed mono, Bayer to grey) against hand-computed bytes."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition.camera.pixel_formats import (
    LUMA_RGB,
    PIXEL_FORMATS,
    bayer_channel_masks,
    bayer_to_grey,
    decode_image,
    pack_mono12,
    payload_bytes,
    pixel_format,
    unpack,
)
from acquisition.errors import DeviceSettingsError


def test_mono12packed_known_bytes() -> None:
    # p0 = 0xABC, p1 = 0x123: GigE legacy layout is [p0>>4, (p1&F)<<4 | p0&F, p1>>4].
    data = bytes([0xAB, 0x3C, 0x12])
    out = unpack(data, pixel_format("Mono12Packed"), 2, 1)
    assert out.tolist() == [[0xABC, 0x123]]


def test_mono12p_known_bytes() -> None:
    # PFNC little-endian bit stream: [p0 & FF, p0>>8 | (p1&F)<<4, p1>>4].
    data = bytes([0xBC, 0x3A, 0x12])
    out = unpack(data, pixel_format("Mono12p"), 2, 1)
    assert out.tolist() == [[0xABC, 0x123]]


def test_mono10p_known_bytes() -> None:
    vals = np.array([0x3FF, 0x001, 0x2AA, 0x155], dtype=np.uint64)
    word = int(sum(int(v) << (10 * i) for i, v in enumerate(vals)))
    data = word.to_bytes(5, "little")
    out = unpack(data, pixel_format("Mono10p"), 4, 1)
    assert out.ravel().tolist() == vals.tolist()


@pytest.mark.parametrize("layout,name", [("mono12packed", "Mono12Packed"),
                                         ("mono12p", "Mono12p")])
def test_pack_unpack_round_trip_odd_width(layout: str, name: str) -> None:
    rng = np.random.default_rng(1)
    img = rng.integers(0, 4096, size=(5, 7), dtype=np.uint16)
    data = pack_mono12(img, layout)
    fmt = pixel_format(name)
    assert len(data) == 3 * 18 and payload_bytes(fmt, 7, 5) == 53  # 35 px padded to 36
    np.testing.assert_array_equal(decode_image(data, fmt, 7, 5), img)


def test_mono16_keeps_all_bits_little_endian() -> None:
    img = np.array([[0, 1, 0xFFFF, 0x1234]], dtype=np.uint16)
    out = decode_image(img.astype("<u2").tobytes(), pixel_format("Mono16"), 4, 1)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, img)


def test_codes_and_names_agree() -> None:
    for name, fmt in PIXEL_FORMATS.items():
        assert pixel_format(fmt.code) is fmt
        assert pixel_format(name) is fmt
        assert (fmt.code >> 16) & 0xFF == fmt.bits_per_pixel
    with pytest.raises(DeviceSettingsError, match="Mono13"):
        pixel_format("Mono13")


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_bayer_demosaic_uniform_colour_is_exact(pattern: str) -> None:
    h, w = 6, 8
    rgb = {"R": 200.0, "G": 100.0, "B": 40.0}
    masks = bayer_channel_masks(pattern, h, w)
    mosaic = sum(np.where(masks[c], rgb[c], 0.0) for c in "RGB").astype(np.uint8)
    grey = bayer_to_grey(mosaic, pattern)
    want = round(sum(wt * rgb[c] for wt, c in zip(LUMA_RGB, "RGB", strict=True)))
    assert np.all(grey == want)


def test_bayer_patterns_differ_and_raw_is_identity() -> None:
    masks = bayer_channel_masks("RGGB", 2, 2)
    assert masks["R"][0, 0] and masks["B"][1, 1] and masks["G"][0, 1] and masks["G"][1, 0]
    masks = bayer_channel_masks("GBRG", 2, 2)
    assert masks["G"][0, 0] and masks["B"][0, 1] and masks["R"][1, 0]
    raw = np.arange(16, dtype=np.uint16).reshape(4, 4)
    assert bayer_to_grey(raw, "RGGB", "raw") is raw


def test_bayer12packed_decodes_to_uint16_grey() -> None:
    h, w = 4, 4
    masks = bayer_channel_masks("BGGR", h, w)
    mosaic = sum(np.where(masks[c], v, 0) for c, v in zip("RGB", (4000, 2000, 1000),
                                                          strict=True)).astype(np.uint16)
    fmt = pixel_format("BayerBG12Packed")
    out = decode_image(pack_mono12(mosaic, "mono12packed"), fmt, w, h)
    assert out.dtype == np.uint16
    assert np.all(out == round(0.299 * 4000 + 0.587 * 2000 + 0.114 * 1000))


def test_short_buffer_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="needs 12 bytes"):
        unpack(b"\0" * 5, pixel_format("Mono12Packed"), 4, 2)
