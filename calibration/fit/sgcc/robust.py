"""Robust weighting of the sGCC residuals: residual norms in sigmas, truncated-Huber cost and
IRLS weights, the hard outlier cut; computed in blocks so that multi-million-pixel fits make
no full-size temporaries."""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, TypeVar

import numpy as np

if TYPE_CHECKING:
    from calibration.fit.sgcc.device import DeviceProblem
    from calibration.fit.sgcc.problem import Problem, Weights

T = TypeVar("T")
_BLOCK = 1 << 16  # pixels per block (small temporaries)
_MAX_THREADS = 4  # NumPy's elementwise loops release the GIL; more threads only contend


def _over_blocks(n: int, work: Callable[[slice], T]) -> list[T]:
    """`work` on consecutive blocks of n pixels, in threads when there are many blocks."""
    blocks = [slice(a, a + _BLOCK) for a in range(0, n, _BLOCK)]
    threads = min(len(os.sched_getaffinity(0)), _MAX_THREADS, len(blocks) // 4)
    if threads < 2:
        return [work(b) for b in blocks]
    with ThreadPoolExecutor(threads) as pool:
        return list(pool.map(work, blocks))


def robust(s: np.ndarray, k: float, cut: float) -> tuple[np.ndarray, np.ndarray]:
    """Truncated-Huber cost per residual norm s and its IRLS weight."""
    hub = np.where(s <= k, s * s, 2 * k * s - k * k)
    cost = np.minimum(hub, 2 * k * cut - k * k)
    wt = np.where(s <= k, 1.0, k / np.maximum(s, 1e-300)) * (s <= cut)
    return cost, wt


def sigma_norm(prob: Problem | DeviceProblem, res: np.ndarray) -> np.ndarray:
    """Residual norms in sigmas (Mahalanobis with diagonal screen sigmas), computed in
    blocks so that multi-million-pixel fits make no full-size temporaries."""
    inv = prob.inv_sigma
    out = np.empty(res.shape[1])

    def block(sl: slice) -> None:
        r0, r1 = res[0, sl] * inv[0, sl], res[1, sl] * inv[1, sl]
        np.sqrt(r0 * r0 + r1 * r1, out=out[sl])

    _over_blocks(len(out), block)
    return out


def block_weights(k: float, cut: float) -> Weights:
    """IRLS weights of a block's residuals e (2,n) mm, ok mask and inverse sigmas (2,n), as
    `robust_terms` gives them from `sigma_norm` (same operations: the same numbers)."""

    def weights(e: np.ndarray, ok: np.ndarray, inv: np.ndarray) -> np.ndarray:
        r0, r1 = e[0] * inv[0], e[1] * inv[1]
        return robust(np.sqrt(r0 * r0 + r1 * r1), k, cut)[1] * ok

    return weights


def robust_terms(
    s: np.ndarray, ok: np.ndarray, k: float, cut: float
) -> tuple[float, np.ndarray, float]:
    """Robust cost of residual norms s (rays missing the plane, not ok, pay the cap), IRLS
    weights (0 where not ok) and the cost over the ok pixels alone; in blocks."""
    wt = np.empty_like(s)
    cap = 2 * k * cut - k * k

    def block(sl: slice) -> tuple[float, int]:
        cost, w = robust(s[sl], k, cut)
        okb = ok[sl]
        np.multiply(w, okb, out=wt[sl])
        return float(cost @ okb), int(okb.size - np.count_nonzero(okb))

    sums = _over_blocks(len(s), block)
    ok_only = sum(c for c, _ in sums)
    return ok_only + cap * sum(m for _, m in sums), wt, ok_only


def outlier_cut(s: np.ndarray, ok: np.ndarray, cut_sigmas: float) -> float:
    """Hard outlier cut: max(cut_sigmas, 5.9 x the median residual norm of the ok pixels).
    The median is only computed when it can matter (more than half the norms above
    cut_sigmas / 5.9); s is 0 where not ok."""
    scale = 4.0 * 1.4826
    n_ok = int(np.count_nonzero(ok))
    if n_ok == 0:
        return max(cut_sigmas, scale)
    if 2 * int(np.count_nonzero(s > cut_sigmas / scale)) < n_ok:
        return cut_sigmas  # the median is at most cut_sigmas / scale
    return max(cut_sigmas, scale * float(np.median(s[ok])))
