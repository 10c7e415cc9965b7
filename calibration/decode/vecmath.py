"""Branch-free atan2 and log for numba loops that LLVM vectorizes (the libm calls it cannot
vectorize cost ~20 ns each per pixel and set). float64 versions accurate to ~1e-12; a
float32 atan2 (Cephes `atanf`'s polynomial, ~2 ulp) for phases kept as float32."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.decode.kernel_cache import drop_stale_kernels

_TAN_PI_8 = math.tan(math.pi / 8)
_LN2 = math.log(2.0)
_SQRT2 = math.sqrt(2.0)


@njit(cache=True, error_model="numpy", inline="always")
def atan2(y: float, x: float) -> float:
    """atan2 for finite arguments (0 for (0, 0)); series of atan on |u| <= tan(pi/8)."""
    ax, ay = abs(x), abs(y)
    hi = max(ax, ay)
    t = min(ax, ay) / (hi if hi > 0.0 else 1.0)
    big = t > _TAN_PI_8
    reduced = (t - 1.0) / (t + 1.0)  # computed unconditionally: a select, not a branch
    u = reduced if big else t
    z = u * u
    p = -1.0 / 27.0
    p = p * z + 1.0 / 25.0
    p = p * z - 1.0 / 23.0
    p = p * z + 1.0 / 21.0
    p = p * z - 1.0 / 19.0
    p = p * z + 1.0 / 17.0
    p = p * z - 1.0 / 15.0
    p = p * z + 1.0 / 13.0
    p = p * z - 1.0 / 11.0
    p = p * z + 1.0 / 9.0
    p = p * z - 1.0 / 7.0
    p = p * z + 1.0 / 5.0
    p = p * z - 1.0 / 3.0
    p = p * z + 1.0
    r = u * p + (0.25 * math.pi if big else 0.0)
    r = 0.5 * math.pi - r if ay > ax else r
    r = math.pi - r if x < 0.0 else r
    return -r if y < 0.0 else r


@njit(cache=True, error_model="numpy", inline="always")
def log_mantissa(m: float) -> float:
    """log(m) for m in [1, 2): 2 atanh((m - 1)/(m + 1)) on [sqrt(1/2), sqrt(2))."""
    half = m > _SQRT2
    m = 0.5 * m if half else m
    s = (m - 1.0) / (m + 1.0)  # (branch-free: LLVM vectorizes the callers' loops)
    z = s * s
    p = 1.0 / 17.0
    p = p * z + 1.0 / 15.0
    p = p * z + 1.0 / 13.0
    p = p * z + 1.0 / 11.0
    p = p * z + 1.0 / 9.0
    p = p * z + 1.0 / 7.0
    p = p * z + 1.0 / 5.0
    p = p * z + 1.0 / 3.0
    p = p * z + 1.0
    return 2.0 * s * p + (_LN2 if half else 0.0)


@njit(cache=True, error_model="numpy", inline="always")
def log_inplace(x, e, m) -> None:
    """x[:] = log(x) for positive normal float64 values; `e`, `m` float64 scratch arrays
    of x's size (exponent and mantissa)."""
    xi, mi = x.view(np.int64), m.view(np.int64)
    for j in range(x.shape[0]):
        b = xi[j]
        e[j] = float(((b >> 52) & 0x7FF) - 1023)
        mi[j] = (b & 0xFFFFFFFFFFFFF) | 0x3FF0000000000000
    for j in range(x.shape[0]):
        x[j] = e[j] * _LN2 + log_mantissa(m[j])


_F32 = np.float32
_TAN_PI_8_32 = np.float32(_TAN_PI_8)
_PI_4_32, _PI_2_32 = np.float32(0.25 * math.pi), np.float32(0.5 * math.pi)
_PI_32 = np.float32(math.pi)


@njit(cache=True, error_model="numpy", inline="always")
def atan2_f32(y, x):
    """atan2 of finite float32 arguments in float32 arithmetic (0 for (0, 0)), within ~2 ulp
    of the correctly rounded value (as NumPy's float32 arctan2): twice the SIMD lanes."""
    ax, ay = abs(x), abs(y)
    hi = max(ax, ay)
    t = min(ax, ay) / (hi if hi > _F32(0.0) else _F32(1.0))
    big = t > _TAN_PI_8_32
    reduced = (t - _F32(1.0)) / (t + _F32(1.0))
    u = reduced if big else t
    z = u * u
    p = _F32(8.05374449538e-2)
    p = p * z - _F32(1.38776856032e-1)
    p = p * z + _F32(1.99777106478e-1)
    p = p * z - _F32(3.33329491539e-1)
    r = p * z * u + u + (_PI_4_32 if big else _F32(0.0))
    r = _PI_2_32 - r if ay > ax else r
    r = _PI_32 - r if x < _F32(0.0) else r
    return -r if y < _F32(0.0) else r


drop_stale_kernels(globals())  # before any kernel runs: no machine code from older sources
