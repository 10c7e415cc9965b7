"""Validate an uploaded maps NPZ (`import-maps`) before anything is stored or fully read.

Order matters: member names and declared uncompressed sizes first (a 1 MB zip can expand
to gigabytes), then each `.npy` header (dtype and shape per docs/formats.md, the declared size
matching the member), then the values (where `mask`: finite coordinates inside the screen
with a margin, finite positive sigmas).
"""

from __future__ import annotations

import io
import zipfile

import numpy as np

from api.problems import Problem
from calibration.shared.maps import DecodedMaps, MapsError, load_maps
from calibration.shared.plan import Plan

DTYPES = {
    "x": np.float64, "y": np.float64, "sigma_x": np.float32, "sigma_y": np.float32,
    "mask": np.bool_, "modulation_x": np.float32, "modulation_y": np.float32,
    "blur_x": np.float32, "blur_y": np.float32,
}
OPTIONAL = ("blur_x", "blur_y")
SCREEN_MARGIN = 0.05  # fraction of the screen extent a coordinate may lie outside it
MAX_META_CHARS = 1 << 16


def _bad(name: str, detail: str) -> Problem:
    return Problem(422, "invalid-maps", f"{name}: {detail}")


def _header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, name: str) -> tuple[tuple, np.dtype]:
    """(shape, dtype) from a member's .npy header; its declared size must fit the member."""
    key = info.filename[:-4]
    with zf.open(info) as fh:
        try:
            version = np.lib.format.read_magic(fh)
            if version not in ((1, 0), (2, 0)):
                raise ValueError(f".npy format version {version}; expected 1.0 or 2.0")
            read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                    else np.lib.format.read_array_header_2_0)
            shape, _fortran, dtype = read(fh)
        except (ValueError, OSError, EOFError) as exc:
            raise _bad(name, f"{key}: not a .npy array ({exc})") from None
    if dtype.hasobject:
        raise _bad(name, f"{key}: object arrays are not allowed")
    n = int(np.prod(shape, dtype=np.int64)) if shape else 1
    if n * dtype.itemsize > info.file_size:
        raise _bad(name, f"{key}: header declares {shape} {dtype}, more than the member holds")
    return shape, dtype


def check_archive(data: bytes, name: str, max_bytes: int) -> tuple[int, int]:
    """Members, sizes, dtypes and shapes of a maps NPZ, without decompressing any array.

    Returns the maps' (H, W).
    """
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, ValueError) as exc:
        raise _bad(name, f"not a phasecal.maps/1 NPZ file (a zip of .npy arrays): {exc}") from None
    with zf:
        infos = zf.infolist()
        total = sum(i.file_size for i in infos)
        if total > max_bytes:
            raise Problem(413, "too-large", f"{name}: the archive expands to {total} bytes, over "
                          f"the upload limit of {max_bytes} bytes")
        allowed = {f"{k}.npy" for k in (*DTYPES, "meta")}
        members = {}
        for info in infos:
            if info.filename not in allowed or info.filename in members:
                raise _bad(name, f"unexpected member {info.filename!r} (expected "
                           f"{sorted(allowed)})")
            members[info.filename] = info
        missing = [k for k in (*DTYPES, "meta") if k not in OPTIONAL
                   and f"{k}.npy" not in members]
        if missing:
            raise _bad(name, f"not a phasecal.maps/1 file, missing keys {missing}")
        shape0: tuple | None = None
        for key, want in DTYPES.items():
            info = members.get(f"{key}.npy")
            if info is None:
                continue
            shape, dtype = _header(zf, info, name)
            if dtype != np.dtype(want):
                raise _bad(name, f"{key}: dtype {dtype}, expected {np.dtype(want)}")
            if len(shape) != 2 or min(shape) < 1:
                raise _bad(name, f"{key}: expected a non-empty 2-D (H, W) array, got {shape}")
            shape0 = shape0 or shape
            if shape != shape0:
                raise _bad(name, f"{key}: shape {shape} differs from x {shape0}")
        meta_shape, meta_dtype = _header(zf, members["meta.npy"], name)
        if meta_shape != () or meta_dtype.kind != "U" or meta_dtype.itemsize > 4 * MAX_META_CHARS:
            raise _bad(name, f"meta: expected a 0-d JSON string, got {meta_dtype} {meta_shape}")
    assert shape0 is not None
    return int(shape0[0]), int(shape0[1])


def check_values(maps: DecodedMaps, name: str, plan: Plan) -> None:
    """Where `mask`: finite x/y inside the screen (with a margin), finite sigmas > 0."""
    m = maps.mask
    if not m.any():
        raise _bad(name, "mask: no valid pixel")
    w, h = plan.screen.width_px, plan.screen.height_px
    for key, extent in (("x", w), ("y", h)):
        vals = getattr(maps, key)[m]
        margin = SCREEN_MARGIN * extent
        bad = ~np.isfinite(vals) | (vals < -0.5 - margin) | (vals > extent - 0.5 + margin)
        if bad.any():
            raise _bad(name, f"{key}: {int(bad.sum())} masked pixels are not finite or lie "
                       f"outside the screen (0..{extent} px with a {margin:g} px margin), "
                       f"e.g. {float(vals[bad][0])!r}")
    for key in ("sigma_x", "sigma_y"):
        vals = getattr(maps, key)[m]
        bad = ~np.isfinite(vals) | (vals <= 0)
        if bad.any():
            raise _bad(name, f"{key}: {int(bad.sum())} masked pixels have a sigma that is not "
                       f"finite and > 0, e.g. {float(vals[bad][0])!r}")


def validated_maps(data: bytes, name: str, plan: Plan, max_bytes: int,
                   camera_size: tuple[int, int] | None) -> DecodedMaps:
    """The maps of an upload once every check passed; 422/413 problems name the key."""
    h, w = check_archive(data, name, max_bytes)
    if camera_size is not None and (w, h) != camera_size:
        raise _bad(name, f"maps are {w}x{h} px but the session's camera is "
                   f"{camera_size[0]}x{camera_size[1]} px")
    try:
        maps = load_maps(data)
    except MapsError as exc:
        raise _bad(name, str(exc).removeprefix("<bytes>: ")) from None
    check_values(maps, name, plan)
    return maps
