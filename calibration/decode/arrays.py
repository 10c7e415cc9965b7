"""Array-namespace helpers: the decoder runs on NumPy or, optionally, CuPy arrays."""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any

import numpy as np

from calibration.extras import install_command


def array_module(name: str | ModuleType | None) -> ModuleType:
    """`numpy` (default) or `cupy` by name or module; a clear error when CuPy is missing."""
    if name is None or name is np or name == "numpy":
        return np
    if isinstance(name, ModuleType):
        return name
    if name == "cupy":
        try:
            return importlib.import_module("cupy")
        except ImportError as exc:
            raise ValueError(f"xp: 'cupy' requested but not importable ({exc}); "
                             f"{install_command(['gpu'])}") from None
    raise ValueError(f"xp: expected 'numpy' or 'cupy', got {name!r}")


def to_host(arr: Any) -> np.ndarray:
    """A NumPy copy/view of an xp array (CuPy arrays are copied from the device)."""
    get = getattr(arr, "get", None)
    return np.asarray(get() if callable(get) else arr)


def chi2_isf(p: float, dof: Any) -> Any:
    """Chi-square inverse survival function (scipy.special: scipy.stats costs ~1 s to import)."""
    from scipy.special import gammainccinv

    return 2.0 * gammainccinv(np.asarray(dof, dtype=np.float64) / 2.0, p)


def special(xp: ModuleType) -> ModuleType:
    """`cupyx.scipy.special` for CuPy, else `scipy.special` (NumPy-compatible namespaces)."""
    if getattr(xp, "__name__", "") == "cupy":
        return importlib.import_module("cupyx.scipy.special")
    return importlib.import_module("scipy.special")
