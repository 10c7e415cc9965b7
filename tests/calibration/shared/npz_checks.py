"""Checks of written NPZ files that several tests share."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from calibration.shared.maps import load_maps


def same_npz(got: Path, want: Path) -> None:
    """Every member equal byte for byte (NaN where the other has NaN; `meta` as JSON), every
    CRC-32 valid, and the maps' documented members, dtypes and meta format."""
    with zipfile.ZipFile(got) as zf:
        assert zf.testzip() is None  # every member's CRC-32 matches
    with np.load(got, allow_pickle=False) as a, np.load(want, allow_pickle=False) as b:
        assert a.files == b.files
        for key in a.files:
            assert a[key].dtype == b[key].dtype and a[key].shape == b[key].shape, key
            if key == "meta":
                assert json.loads(str(a[key])) == json.loads(str(b[key]))
            else:
                assert a[key].tobytes() == b[key].tobytes(), key
    load_maps(got)  # docs/formats.md members, dtypes, meta format
