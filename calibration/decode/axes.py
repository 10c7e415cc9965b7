"""From per-period fits to positions, sigmas, blur and reason codes for a chunk of pixels.

Two implementations of the same rules: `decode_axes_xp` in array-namespace operations
(NumPy or CuPy) and `decode_axes_compiled`, which hands the per-set fits to the numba
kernel (kernel.py) for NumPy arrays.
"""

from __future__ import annotations

import functools
import math
from types import ModuleType
from typing import Any

import numpy as np

from calibration.decode.accumulate import SetSums
from calibration.decode.arrays import chi2_isf, to_host
from calibration.decode.blur import fit_blur
from calibration.decode.options import DecodeOptions
from calibration.decode.phase import SetFit
from calibration.decode.unwrap import fuse_axis
from calibration.decode.validity import AxisChecks, classify
from calibration.shared.plan import Plan

# Periods finer than the coarsest enter the fusion and the blur fit only above this
# modulation SNR: below it the phase noise is no longer Gaussian (the linearized sigma lies).
MIN_PERIOD_SNR = 4.0


@functools.lru_cache(maxsize=16)
def chi2_limits(max_dof: int, p: float) -> np.ndarray:
    """Chi-square consistency limit by number of fused finer periods (inf for none)."""
    return np.array([math.inf] + [chi2_isf(p, d) for d in range(1, max_dof + 1)])


def decode_axes_xp(
    xp: ModuleType, plan: Plan, sets: list[SetSums], fits: list[SetFit], variances: list[Any],
    contrast_snr: Any, opt: DecodeOptions, out: dict[str, np.ndarray], sl: slice,
) -> np.ndarray:
    """Array-namespace path: write the chunk's outputs into `out`; return its reason codes."""
    checks: list[AxisChecks] = []
    for axis in plan.axes():
        idx = [k for k, s in enumerate(sets) if s.layout.axis == axis]
        periods = [sets[k].layout.period_px for k in idx]
        pos, sig, use, mods, mod_sig = [], [], [], [], []
        for k, period in zip(idx, periods, strict=True):
            f, var = fits[k], variances[k]
            s_b = xp.sqrt(var * f.modulation_var())
            mod = f.modulation
            sig_c = (period / (2.0 * math.pi)) * xp.sqrt(var * f.phase_var())
            usable = f.ok & (mod >= MIN_PERIOD_SNR * s_b) & xp.isfinite(sig_c)
            pos.append(f.position(xp, period))
            sig.append(xp.where(usable, sig_c, period))
            use.append(usable)
            mods.append(mod)
            mod_sig.append(s_b)
        extent = plan.screen.extent_px(axis)
        post = fuse_axis(xp, pos, sig, periods, use, extent)
        amps = [sets[k].layout.amplitude for k in idx]
        blur, _ = fit_blur(xp, mods, mod_sig, amps, periods, MIN_PERIOD_SNR)
        limits = xp.asarray(chi2_limits(len(idx) - 1, opt.consistency_p))
        checks.append(
            AxisChecks(
                anchor_ok=fits[idx[0]].ok,
                anchor_snr=mods[0] / xp.where(mod_sig[0] > 0, mod_sig[0], xp.inf),
                ambiguity=post.ambiguity,
                chi2=post.chi2,
                chi2_limit=limits[post.dof.astype(xp.int64)],
                position=post.position,
                sigma=post.sigma,
                blur=blur,
                extent_px=extent,
            )
        )
        out[axis][sl] = to_host(post.position)
        out[f"sigma_{axis}"][sl] = to_host(post.sigma)
        out[f"modulation_{axis}"][sl] = to_host(mods[-1])
        out[f"blur_{axis}"][sl] = to_host(blur)
    return to_host(
        classify(
            xp,
            contrast_snr,
            checks,
            min_contrast_snr=opt.min_contrast_snr,
            min_modulation_snr=opt.min_modulation_snr,
            max_ambiguity=opt.max_ambiguity,
            screen_margin_sigma=opt.screen_margin_sigma,
            edge_margin_blur=opt.edge_margin_blur,
            max_sigma_px=opt.max_sigma_px,
        )
    )


def _rows(values: list[Any], n: int, dtype: Any) -> np.ndarray:
    """Stack per-set arrays (or scalars) into one contiguous (S, n) array."""
    out = np.empty((len(values), n), dtype=dtype)
    for k, v in enumerate(values):
        out[k] = v
    return out


def decode_axes_compiled(
    plan: Plan, sets: list[SetSums], fits: list[SetFit], variances: list[Any],
    contrast_snr: np.ndarray, opt: DecodeOptions, planes: dict[str, np.ndarray], sl: slice,
) -> np.ndarray:
    """Compiled path: the kernel writes `planes` (each (2, npix), rows x, y) over `sl`."""
    from calibration.decode.kernel import finish_pixels

    n = contrast_snr.shape[0]
    f32 = np.float32
    axis_of = np.array([0 if s.layout.axis == "x" else 1 for s in sets], dtype=np.int64)
    per_axis = max(int((axis_of == a).sum()) for a in (0, 1))
    limits = chi2_limits(max(per_axis - 1, 0), opt.consistency_p)
    limits = np.concatenate([limits, np.full(len(sets) + 1 - limits.size, np.inf)])
    params = np.array([opt.min_contrast_snr, opt.min_modulation_snr, opt.max_ambiguity,
                       opt.screen_margin_sigma, opt.edge_margin_blur, opt.max_sigma_px,
                       MIN_PERIOD_SNR])
    extents = np.array([plan.screen.extent_px(a) for a in ("x", "y")], dtype=np.float64)
    reason = np.empty(n, dtype=np.uint8)
    finish_pixels(
        _rows([f.alpha for f in fits], n, f32), _rows([f.beta for f in fits], n, f32),
        _rows([f.position(np, s.layout.period_px) for f, s in zip(fits, sets, strict=True)],
              n, f32),
        _rows(variances, n, f32), _rows([f.c_aa for f in fits], n, f32),
        _rows([f.c_bb for f in fits], n, f32), _rows([f.c_ab for f in fits], n, f32),
        _rows([f.ok for f in fits], n, np.bool_), axis_of,
        np.array([s.layout.period_px for s in sets]),
        np.array([s.layout.amplitude for s in sets]),
        np.ascontiguousarray(contrast_snr, dtype=np.float64), limits, extents, params,
        planes["position"][:, sl], planes["sigma"][:, sl], planes["modulation"][:, sl],
        planes["blur"][:, sl], reason,
    )
    return reason
