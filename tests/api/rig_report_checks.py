"""Reading a rig report page in tests: its tables' cells, and the extrinsics row checked
against the rig file's extrinsics (baseline, and the 1-sigma of translation and rotation)."""

from __future__ import annotations

import re
from typing import Any

import numpy as np
import pytest


def table_rows(page: str, table_id: str) -> list[list[str]]:
    """The data cells of a report table, row by row."""
    body = re.search(rf"<table id='{table_id}'.*?</table>", page, re.S).group(0)
    return [re.findall(r"<td>(.*?)</td>", row) for row in re.findall(r"<tr>(.*?)</tr>", body)
            if "<td>" in row]


def check_extrinsics_row(page: str, camera: str, ext: dict[str, Any]) -> list[str]:
    """The page's one extrinsics row names `camera` and shows `ext`'s (a rig file's
    `extrinsics`) baseline and 1-sigmas; the row."""
    sd = np.sqrt(np.diag(ext["covariance"]))
    (row,) = table_rows(page, "extrinsics")
    assert row[0] == camera
    assert float(row[1]) == pytest.approx(
        np.linalg.norm(np.asarray(ext["R"]).T @ np.asarray(ext["t_mm"])), rel=1e-3)
    assert float(row[4]) == pytest.approx(np.linalg.norm(sd[3:]), rel=1e-2)
    assert float(row[5]) == pytest.approx(np.linalg.norm(sd[:3]) * 1e3, rel=1e-2)
    return row
