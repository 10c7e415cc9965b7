"""Points in and out of the model routes (`api.routes.points`): arrays from body rows, null
where a row has no answer, every answer at its input's index."""

from __future__ import annotations

import json

import numpy as np

from api.routes.points import json_rows, point_rows


def test_body_rows_become_a_float_array_of_the_given_width() -> None:
    a = point_rows([(1, 2.5, 3), (4.0, 5.0, 6.0)], 3)
    assert a.dtype == np.float64 and a.shape == (2, 3)
    assert point_rows([], 2).shape == (0, 2)


def test_non_finite_values_become_null_and_rows_keep_their_index() -> None:
    out = json_rows(np.array([[1.5, np.nan], [np.inf, -2.0], [np.float32(0.25), 3]]))
    assert out == [[1.5, None], [None, -2.0], [0.25, 3.0]]
    assert all(type(v) is float for row in out for v in row if v is not None)
    assert json.loads(json.dumps(out, allow_nan=False)) == out
