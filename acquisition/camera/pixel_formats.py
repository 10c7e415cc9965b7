"""GenICam (PFNC) pixel formats: codes, unpacking of packed formats and Bayer-to-grey.

Cameras deliver raw bytes; the controller wants a 2-D grey array that keeps every
significant bit (uint8 for 8-bit data, uint16 otherwise). All functions are vectorized.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from acquisition.errors import DeviceSettingsError


@dataclass(frozen=True)
class PixelFormat:
    """One pixel format: PFNC code, bits stored per pixel, significant bits, layout."""

    name: str
    code: int
    bits_per_pixel: int  # bits each pixel occupies in the buffer
    bit_depth: int  # significant bits of each value
    layout: str  # "mono", "mono12packed" (GigE legacy), "mono12p"/"mono10p" (PFNC), "rgb", "bgr"
    bayer: str | None = None  # 2x2 pattern read row-major, e.g. "RGGB"


def _fmt(name: str, code: int, bpp: int, depth: int, layout: str = "mono", bayer=None):
    return PixelFormat(name, code, bpp, depth, layout, bayer)


PIXEL_FORMATS: dict[str, PixelFormat] = {
    f.name: f
    for f in [
        _fmt("Mono8", 0x01080001, 8, 8),
        _fmt("Mono10", 0x01100003, 16, 10),
        _fmt("Mono10Packed", 0x010C0004, 12, 10, "mono10packed"),
        _fmt("Mono10p", 0x010A0046, 10, 10, "mono10p"),
        _fmt("Mono12", 0x01100005, 16, 12),
        _fmt("Mono12Packed", 0x010C0006, 12, 12, "mono12packed"),
        _fmt("Mono12p", 0x010C0047, 12, 12, "mono12p"),
        _fmt("Mono14", 0x01100025, 16, 14),
        _fmt("Mono16", 0x01100007, 16, 16),
        _fmt("BayerGR8", 0x01080008, 8, 8, bayer="GRBG"),
        _fmt("BayerRG8", 0x01080009, 8, 8, bayer="RGGB"),
        _fmt("BayerGB8", 0x0108000A, 8, 8, bayer="GBRG"),
        _fmt("BayerBG8", 0x0108000B, 8, 8, bayer="BGGR"),
        _fmt("BayerGR12", 0x01100010, 16, 12, bayer="GRBG"),
        _fmt("BayerRG12", 0x01100011, 16, 12, bayer="RGGB"),
        _fmt("BayerGB12", 0x01100012, 16, 12, bayer="GBRG"),
        _fmt("BayerBG12", 0x01100013, 16, 12, bayer="BGGR"),
        _fmt("BayerGR12Packed", 0x010C002A, 12, 12, "mono12packed", "GRBG"),
        _fmt("BayerRG12Packed", 0x010C002B, 12, 12, "mono12packed", "RGGB"),
        _fmt("BayerGB12Packed", 0x010C002C, 12, 12, "mono12packed", "GBRG"),
        _fmt("BayerBG12Packed", 0x010C002D, 12, 12, "mono12packed", "BGGR"),
        _fmt("BayerGR12p", 0x010C0057, 12, 12, "mono12p", "GRBG"),
        _fmt("BayerRG12p", 0x010C0059, 12, 12, "mono12p", "RGGB"),
        _fmt("BayerGB12p", 0x010C0055, 12, 12, "mono12p", "GBRG"),
        _fmt("BayerBG12p", 0x010C0053, 12, 12, "mono12p", "BGGR"),
        _fmt("BayerGR16", 0x0110002E, 16, 16, bayer="GRBG"),
        _fmt("BayerRG16", 0x0110002F, 16, 16, bayer="RGGB"),
        _fmt("BayerGB16", 0x01100030, 16, 16, bayer="GBRG"),
        _fmt("BayerBG16", 0x01100031, 16, 16, bayer="BGGR"),
        _fmt("RGB8", 0x02180014, 24, 8, "rgb"),
        _fmt("BGR8", 0x02180015, 24, 8, "bgr"),
    ]
}
_BY_CODE = {f.code: f for f in PIXEL_FORMATS.values()}

# Luma weights (ITU-R BT.601) used to turn colour into grey.
LUMA_RGB = (0.299, 0.587, 0.114)


def pixel_format(name_or_code: str | int) -> PixelFormat:
    """Look up a pixel format by GenICam name or PFNC code, with a clear error."""
    fmt = (
        _BY_CODE.get(name_or_code)
        if isinstance(name_or_code, int)
        else PIXEL_FORMATS.get(name_or_code)
    )
    if fmt is None:
        shown = hex(name_or_code) if isinstance(name_or_code, int) else repr(name_or_code)
        raise DeviceSettingsError(
            f"pixel_format: unsupported pixel format {shown}; supported: {sorted(PIXEL_FORMATS)}"
        )
    return fmt


def payload_bytes(fmt: PixelFormat, width: int, height: int) -> int:
    """Bytes one image of this format and size occupies."""
    return (width * height * fmt.bits_per_pixel + 7) // 8


def _unpack_12_msb_first(b: np.ndarray) -> np.ndarray:
    """GigE legacy Mono12Packed: [p0[11:4], p1[3:0] << 4 | p0[3:0], p1[11:4]]."""
    b = b.reshape(-1, 3).astype(np.uint16)
    p0 = (b[:, 0] << 4) | (b[:, 1] & 0x0F)
    p1 = (b[:, 2] << 4) | (b[:, 1] >> 4)
    return np.stack([p0, p1], axis=1).reshape(-1)


def _unpack_12_lsb_first(b: np.ndarray) -> np.ndarray:
    """PFNC Mono12p: little-endian bit stream, p0 = byte0 | (byte1 & 0xF) << 8, ..."""
    b = b.reshape(-1, 3).astype(np.uint16)
    p0 = b[:, 0] | ((b[:, 1] & 0x0F) << 8)
    p1 = (b[:, 1] >> 4) | (b[:, 2] << 4)
    return np.stack([p0, p1], axis=1).reshape(-1)


def _unpack_10_packed(b: np.ndarray) -> np.ndarray:
    """GigE legacy Mono10Packed: like Mono12Packed with 2 low bits per pixel in byte1."""
    b = b.reshape(-1, 3).astype(np.uint16)
    p0 = (b[:, 0] << 2) | (b[:, 1] & 0x03)
    p1 = (b[:, 2] << 2) | ((b[:, 1] >> 4) & 0x03)
    return np.stack([p0, p1], axis=1).reshape(-1)


def _unpack_10p(b: np.ndarray) -> np.ndarray:
    """PFNC Mono10p: 4 pixels in 5 bytes, little-endian bit stream."""
    b = b.reshape(-1, 5).astype(np.uint16)
    p0 = b[:, 0] | ((b[:, 1] & 0x03) << 8)
    p1 = (b[:, 1] >> 2) | ((b[:, 2] & 0x0F) << 6)
    p2 = (b[:, 2] >> 4) | ((b[:, 3] & 0x3F) << 4)
    p3 = (b[:, 3] >> 6) | (b[:, 4] << 2)
    return np.stack([p0, p1, p2, p3], axis=1).reshape(-1)


_UNPACKERS = {
    "mono12packed": (_unpack_12_msb_first, 3, 2),
    "mono12p": (_unpack_12_lsb_first, 3, 2),
    "mono10packed": (_unpack_10_packed, 3, 2),
    "mono10p": (_unpack_10p, 5, 4),
}


def unpack(data: bytes | np.ndarray, fmt: PixelFormat, width: int, height: int) -> np.ndarray:
    """Raw buffer bytes -> (H, W) values (or (H, W, 3) for RGB/BGR), every bit kept."""
    raw = np.frombuffer(data, dtype=np.uint8) if isinstance(data, bytes | bytearray) else data
    raw = np.asarray(raw, dtype=np.uint8).reshape(-1)
    need = payload_bytes(fmt, width, height)
    if raw.size < need:
        raise ValueError(
            f"{fmt.name} {width}x{height} needs {need} bytes, the buffer has {raw.size}"
        )
    n = width * height
    if fmt.layout in _UNPACKERS:
        fn, group_bytes, group_px = _UNPACKERS[fmt.layout]
        groups = -(-n // group_px)
        padded = np.zeros(groups * group_bytes, np.uint8)
        take = min(raw.size, padded.size)
        padded[:take] = raw[:take]
        return fn(padded)[:n].reshape(height, width)
    if fmt.layout in ("rgb", "bgr"):
        return raw[: n * 3].reshape(height, width, 3)
    if fmt.bits_per_pixel == 8:
        return raw[:n].reshape(height, width)
    return raw[: 2 * n].view("<u2").reshape(height, width)


def pack_mono12(values: np.ndarray, layout: str = "mono12packed") -> bytes:
    """Inverse of `unpack` for the 12-bit packed layouts (tests, simulated cameras)."""
    v = np.asarray(values, dtype=np.uint16).reshape(-1)
    if v.size % 2:
        v = np.append(v, np.uint16(0))
    if np.any(v > 0x0FFF):
        raise ValueError("pack_mono12: values must fit in 12 bits")
    p0, p1 = v[0::2], v[1::2]
    if layout == "mono12packed":
        out = np.stack([p0 >> 4, ((p1 & 0x0F) << 4) | (p0 & 0x0F), p1 >> 4], axis=1)
    elif layout == "mono12p":
        out = np.stack([p0 & 0xFF, (p0 >> 8) | ((p1 & 0x0F) << 4), p1 >> 4], axis=1)
    else:
        raise ValueError(f"pack_mono12: layout must be 'mono12packed' or 'mono12p', got {layout!r}")
    return out.astype(np.uint8).tobytes()


_BOX3 = np.ones((3, 3), np.float32)


def _box3(a: np.ndarray) -> np.ndarray:
    """3x3 sum with zero padding outside the image (float32, exact for 16-bit sums)."""
    return cv2.filter2D(a, -1, _BOX3, borderType=cv2.BORDER_CONSTANT)


def bayer_channel_masks(pattern: str, height: int, width: int) -> dict[str, np.ndarray]:
    """Boolean masks of the R, G and B sites of a Bayer mosaic (pattern read row-major)."""
    if len(pattern) != 4 or sorted(pattern) != ["B", "G", "G", "R"]:
        raise ValueError(f"bayer pattern must be a 2x2 arrangement like 'RGGB', got {pattern!r}")
    return _masks(pattern, height, width)


@functools.lru_cache(maxsize=8)
def _masks(pattern: str, height: int, width: int) -> dict[str, np.ndarray]:
    yy, xx = np.mgrid[0:height, 0:width]
    site = (yy % 2) * 2 + (xx % 2)
    return {c: np.isin(site, [i for i, p in enumerate(pattern) if p == c]) for c in "RGB"}


@functools.lru_cache(maxsize=8)
def _interp_weights(pattern: str, height: int, width: int) -> tuple[np.ndarray, ...]:
    """Per channel: (mask as float32, luma weight / number of same-colour neighbours)."""
    out = []
    for weight, c in zip(LUMA_RGB, "RGB", strict=True):
        m = _masks(pattern, height, width)[c].astype(np.float32)
        out += [m, np.float32(weight) / _box3(m)]
    return tuple(out)


def bayer_to_grey(raw: np.ndarray, pattern: str, method: str = "demosaic") -> np.ndarray:
    """Bayer mosaic -> grey image of the same size and dtype.

    'demosaic' interpolates each colour plane bilinearly (normalized 3x3 convolution,
    exact for uniform colour, borders included) and mixes them with BT.601 luma weights.
    'raw' returns the mosaic unchanged: for phase-shift decoding each pixel's own gain is
    absorbed by the per-pixel contrast, so the mosaic is already a valid grey image with
    no interpolation blur.
    """
    if method == "raw":
        return raw
    if method != "demosaic":
        raise DeviceSettingsError(f"bayer: method must be 'demosaic' or 'raw', got {method!r}")
    h, w = raw.shape
    bayer_channel_masks(pattern, h, w)  # validates the pattern
    weights = _interp_weights(pattern, h, w)
    x = raw.astype(np.float32)
    grey = np.zeros((h, w), np.float32)
    for i, luma in enumerate(LUMA_RGB):
        m, scale = weights[2 * i], weights[2 * i + 1]
        # Own sites keep their value; others take the mean of same-colour neighbours.
        grey += np.where(m > 0, np.float32(luma) * x, _box3(x * m) * scale)
    top = np.iinfo(raw.dtype).max
    return np.clip(np.rint(grey), 0, top).astype(raw.dtype)


def to_grey(values: np.ndarray, fmt: PixelFormat, bayer_method: str = "demosaic") -> np.ndarray:
    """Unpacked values -> 2-D grey (uint8 for 8-bit formats, uint16 otherwise)."""
    if fmt.layout in ("rgb", "bgr"):
        rgb = values[..., ::-1] if fmt.layout == "bgr" else values
        grey = rgb.astype(np.float64) @ np.asarray(LUMA_RGB)
        return np.clip(np.rint(grey), 0, 255).astype(np.uint8)
    if fmt.bayer is not None:
        return bayer_to_grey(values, fmt.bayer, bayer_method)
    return values


def decode_image(
    data: bytes | np.ndarray,
    fmt: PixelFormat,
    width: int,
    height: int,
    bayer_method: str = "demosaic",
) -> np.ndarray:
    """Raw buffer -> grey (H, W) image keeping all significant bits (a fresh copy)."""
    out = to_grey(unpack(data, fmt, width, height), fmt, bayer_method)
    return np.array(out, copy=True)
