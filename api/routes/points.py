"""Point lists of request bodies as arrays, and arrays back as JSON rows, for the routes that
apply a fitted model to points (project, unproject, undistort-points).

Rows that have no answer (a point the model does not image, a ray that misses the virtual
pinhole) are NaN in the arrays and null in the JSON: JSON has no NaN, and a null row keeps
every answer at the index of its input (the REST form of the NaN rows of `phasecal project`,
docs/formats.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def point_rows(values: Sequence[Sequence[float]], width: int) -> np.ndarray:
    """A validated body's points (tuples of `width` numbers) as an (N, width) float array."""
    return np.asarray(values, np.float64).reshape(-1, width)


def json_rows(a: np.ndarray) -> list[list[float | None]]:
    """An (N, K) array as JSON rows of plain floats, null where a value is not finite."""
    return [[None if not np.isfinite(v) else float(v) for v in row] for row in a]
