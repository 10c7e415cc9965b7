"""Basis of the sGCC fit's free directions (gauge null space) that keeps its sparsity.

The gauge constraints (`lm.gauge_constraints`) touch only the coefficients of the 16 control
points around the sensor center; every other parameter is free as it is. So the null space
is the identity on the untouched parameters plus a small dense block on the touched ones:
Z = P [[I, 0], [0, N]]. Reducing the ~700x700 normal matrix (Z^T H Z) and expanding steps
and the covariance then cost copies and products with N (~64x58) instead of dense
700x700x700 products (1.3 GFLOP each, about 0.1 s per LM iteration on one core).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import null_space


@dataclass(frozen=True)
class GaugeBasis:
    """Z: the columns `keep` pass through, the columns `mixed` are combined by `basis`
    (len(mixed), k); every other parameter is held fixed (zero in Z)."""

    n: int
    keep: np.ndarray
    mixed: np.ndarray
    basis: np.ndarray

    @classmethod
    def null_space_of(cls, constraints: np.ndarray) -> GaugeBasis:
        """Orthonormal basis of {x : constraints @ x = 0}."""
        n = constraints.shape[1]
        touched = np.flatnonzero(np.any(constraints != 0, axis=0))
        keep = np.setdiff1d(np.arange(n), touched)
        return cls(n, keep, touched, null_space(constraints[:, touched]))

    @classmethod
    def selection(cls, n: int, columns: np.ndarray) -> GaugeBasis:
        """Only `columns` free (e.g. the poses of a fit with the spline held fixed)."""
        return cls(n, np.asarray(columns), np.zeros(0, dtype=np.int64), np.zeros((0, 0)))

    @property
    def size(self) -> int:
        """Number of free directions."""
        return len(self.keep) + self.basis.shape[1]

    def reduce(self, h: np.ndarray) -> np.ndarray:
        """Z^T H Z of a symmetric (n, n) matrix."""
        k, m, b = self.keep, self.mixed, self.basis
        hkm = h[np.ix_(k, m)] @ b
        return np.block([[h[np.ix_(k, k)], hkm], [hkm.T, b.T @ h[np.ix_(m, m)] @ b]])

    def reduce_vector(self, g: np.ndarray) -> np.ndarray:
        """Z^T g."""
        return np.concatenate([g[self.keep], self.basis.T @ g[self.mixed]])

    def expand(self, x: np.ndarray) -> np.ndarray:
        """Z x: a reduced vector as a full parameter vector."""
        out = np.zeros(self.n)
        out[self.keep] = x[: len(self.keep)]
        out[self.mixed] = self.basis @ x[len(self.keep) :]
        return out

    def expand_matrix(self, c: np.ndarray) -> np.ndarray:
        """Z C Z^T of a symmetric reduced matrix (the covariance in full coordinates)."""
        nk, k, m, b = len(self.keep), self.keep, self.mixed, self.basis
        out = np.zeros((self.n, self.n))
        out[np.ix_(k, k)] = c[:nk, :nk]
        cross = c[:nk, nk:] @ b.T
        out[np.ix_(k, m)] = cross
        out[np.ix_(m, k)] = cross.T
        out[np.ix_(m, m)] = b @ c[nk:, nk:] @ b.T
        return out
