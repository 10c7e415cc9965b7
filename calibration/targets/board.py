"""Board geometry: a target description ("chessboard:9x6:25" or
"charuco:11x8:15:11:DICT_5X5_100") and the target points it defines, in mm, in the board's
frame (x along the columns, y along the rows, z = 0 for a flat board)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

TargetKind = Literal["chessboard", "charuco"]
_SIZE = re.compile(r"^(\d+)x(\d+)$")


class TargetSpecError(ValueError):
    """A target description that cannot be parsed; the message says which part and why."""


def _positive(text: str, what: str, spec: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise TargetSpecError(f"target {spec!r}: {what}: expected a number, got {text!r}") from None
    if not (np.isfinite(value) and value > 0):
        raise TargetSpecError(f"target {spec!r}: {what}: expected > 0, got {text!r}")
    return value


@dataclass(frozen=True)
class TargetSpec:
    """A printed board. Chessboard: COLSxROWS inner corners (OpenCV's pattern size). ChArUco:
    COLSxROWS squares, square and marker side in mm and the ArUco dictionary name."""

    kind: TargetKind
    cols: int
    rows: int
    square_mm: float
    marker_mm: float | None = None
    dictionary: str | None = None

    @classmethod
    def parse(cls, text: str) -> TargetSpec:
        """`chessboard:COLSxROWS:SQUARE_MM` or `charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT`."""
        parts = text.strip().split(":")
        kind = parts[0].lower()
        if kind not in ("chessboard", "charuco"):
            raise TargetSpecError(f"target {text!r}: kind: expected 'chessboard' or 'charuco', "
                                  f"got {parts[0]!r}")
        want = 3 if kind == "chessboard" else 5
        if len(parts) != want:
            form = ("chessboard:COLSxROWS:SQUARE_MM" if kind == "chessboard"
                    else "charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT")
            raise TargetSpecError(f"target {text!r}: expected {form}")
        size = _SIZE.match(parts[1].lower())
        if size is None:
            raise TargetSpecError(f"target {text!r}: size: expected COLSxROWS, got {parts[1]!r}")
        cols, rows = int(size[1]), int(size[2])
        least = 2 if kind == "chessboard" else 3
        if cols < least or rows < least:
            unit = "inner corners" if kind == "chessboard" else "squares"
            raise TargetSpecError(f"target {text!r}: size: expected >= {least} {unit} each "
                                  f"way, got {cols}x{rows}")
        square = _positive(parts[2], "square_mm", text)
        if kind == "chessboard":
            return cls("chessboard", cols, rows, square)
        marker = _positive(parts[3], "marker_mm", text)
        if marker >= square:
            raise TargetSpecError(f"target {text!r}: marker_mm: must be smaller than the square "
                                  f"({square:g} mm), got {marker:g}")
        name = parts[4].upper()
        if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
            known = sorted(d for d in dir(cv2.aruco) if d.startswith("DICT_"))
            raise TargetSpecError(f"target {text!r}: dictionary: unknown {parts[4]!r}; known: "
                                  f"{', '.join(known)}")
        return cls("charuco", cols, rows, square, marker, name)

    def describe(self) -> str:
        """The description `parse` reads back."""
        base = f"{self.kind}:{self.cols}x{self.rows}:{self.square_mm:g}"
        if self.kind == "chessboard":
            return base
        return f"{base}:{self.marker_mm:g}:{self.dictionary}"

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board object (ChArUco only), lengths in mm."""
        if self.kind != "charuco":
            raise TargetSpecError(f"{self.describe()}: not a ChArUco board")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_mm, self.marker_mm,
                                      dictionary)

    def points(self) -> np.ndarray:
        """Float64 (N, 3) target points in mm, in the order the detector reports ids
        (row-major; ChArUco: OpenCV's corner ids)."""
        if self.kind == "charuco":
            return np.asarray(self.charuco_board().getChessboardCorners(), dtype=np.float64)
        cols, rows = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        xy = np.stack([cols.ravel(), rows.ravel()], axis=1) * self.square_mm
        return np.column_stack([xy, np.zeros(len(xy))]).astype(np.float64)

    @property
    def corner_grid(self) -> tuple[int, int]:
        """(columns, rows) of the inner-corner grid."""
        if self.kind == "charuco":
            return self.cols - 1, self.rows - 1
        return self.cols, self.rows
